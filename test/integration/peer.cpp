// lcmx_test_peer: the other processes of the integration tests.
//
//   pub  --channel C --type pose|image|bench --count N --rate HZ --size BYTES
//        [--subscribers K] [--id NAME] [--local-sub] [--hold] [--history N] [--also D ...]
//     Advertises, prints "READY", waits (deadline --timeout-ms) for K matched subscribers,
//     prints "MATCHED <k>", publishes N messages (N = 0: until killed or told "quit"), prints
//     "PUBLISHED <n>". With --hold it then waits for "quit" on stdin before exiting (so
//     subscribers can drain before the goodbye). --local-sub adds an in-process subscriber
//     on another node (intra path). --id tags every message (header.frame_id / bench data),
//     so subscribers check order per publisher.
//   sub  --channel C [--channel D ...] --type ... [--expect N] [--publishers K]
//     Subscribes, prints "READY", optionally waits for K publishers per channel and prints
//     "MATCHED". Exits when every channel received --expect messages (N > 0), or on "quit".
//     "status" on stdin prints the summary without exiting. Every role: "udp" on stdin prints
//     the UDP groups' counters and receive filters ("UDP ..." lines, then "UDP END").
//   idle --channel C --type ...   advertise (and with --local-sub subscribe), "READY", wait for "quit".
//   many --channel C --topics N --count R   raw publishers on C_0..C_<N-1>, each matched, then R
//        rounds of one 8-byte message per channel; "PUBLISHED <n>", wait for "quit".
//
// Summary, one line per channel, then "END":
//   SUMMARY channel=C received=R first=F last=L min=M duplicates=D out_of_order=O gaps=G drops=X
//           decode_errors=E bad_content=B publishers=P paths=shm,intra sources=S errors=N
// followed by N lines "ERROR <text>". Events of Runtime::on_event print as
//   "EVENT <kind> <channel|-> <message>".
// Any mismatching --type on a channel is the "type mismatch" mode: the runtime does the rest.
// SIGTERM/SIGINT or "quit" exit cleanly (goodbye); the overall --timeout-ms exits with 3.
#include <CLI/CLI.hpp>
#include <poll.h>
#include <signal.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <iostream>
#include <map>
#include <mutex>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "lcmx/core.hpp"
#include "lcmx_examples/bench_t.hpp"
#include "lcmx_examples/image_t.hpp"
#include "lcmx_examples/pose_t.hpp"

namespace {

using Clock = std::chrono::steady_clock;
using namespace std::chrono_literals;

std::mutex g_out_mu;
std::atomic<bool> g_stop{false};
std::atomic<bool> g_quit{false};  // "quit" on stdin or a signal

void say(const std::string& line) {
  std::lock_guard lock(g_out_mu);
  std::fwrite(line.data(), 1, line.size(), stdout);
  std::fputc('\n', stdout);
  std::fflush(stdout);
}

std::int64_t now_ns() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return std::int64_t{ts.tv_sec} * 1'000'000'000 + ts.tv_nsec;
}

// Content pattern: byte i of message `seq` is (i * 131 + seq * 7) & 0xff.
inline std::uint8_t pattern(std::size_t i, std::int64_t seq) {
  return static_cast<std::uint8_t>((i * 131u + static_cast<std::uint64_t>(seq) * 7u) & 0xffu);
}

template <class V>
void fill(V& data, std::int64_t seq) {
  for (std::size_t i = 0; i < data.size(); ++i) data[i] = static_cast<typename V::value_type>(pattern(i, seq));
}

template <class V>
bool check(const V& data, std::int64_t seq, std::size_t from = 0) {
  for (std::size_t i = from; i < data.size(); ++i)
    if (static_cast<std::uint8_t>(data[i]) != pattern(i, seq)) return false;
  return true;
}

// "UDP <group> packets_received=... filtered=... kernel_filtered=0|1 channels=all|N discovery=0|1
// markers_by_channel=0|1" for both groups (Runtime::udp_stats), on "udp".
void say_udp(const lcmx::Runtime& rt) {
  const auto u = rt.udp_stats();
  for (const auto& [name, g] : {std::pair{"host-local", u.host_local}, std::pair{"vehicle", u.vehicle}}) {
    if (!g.open) continue;
    say(std::string("UDP ") + name + " packets_received=" + std::to_string(g.packets_received) +
        " messages_received=" + std::to_string(g.messages_received) + " filtered=" + std::to_string(g.filtered_dropped) +
        " kernel_filtered=" + (g.kernel_filtered ? "1" : "0") +
        " channels=" + (g.all_channels ? std::string("all") : std::to_string(g.channels)) +
        " discovery=" + (g.discovery ? "1" : "0") + " markers_by_channel=" + (g.markers_by_channel ? "1" : "0"));
  }
  say("UDP END");
}

// Reads commands from stdin on its own thread: "quit", "status" and "udp" (EOF = quit).
class Stdin {
 public:
  std::atomic<int> status_requests{0};
  const lcmx::Runtime* runtime = nullptr;  // for "udp"
  void start() {
    thread_ = std::thread([this] {
      std::string buf;
      while (!g_stop.load()) {
        pollfd p{STDIN_FILENO, POLLIN, 0};
        if (::poll(&p, 1, 100) <= 0) continue;
        char chunk[256];
        const ssize_t n = ::read(STDIN_FILENO, chunk, sizeof chunk);
        if (n <= 0) {
          g_quit = true;
          return;
        }
        buf.append(chunk, static_cast<std::size_t>(n));
        for (auto nl = buf.find('\n'); nl != std::string::npos; nl = buf.find('\n')) {
          const std::string cmd = buf.substr(0, nl);
          buf.erase(0, nl + 1);
          if (cmd == "quit") g_quit = true;
          else if (cmd == "status") ++status_requests;
          else if (cmd == "udp" && runtime) say_udp(*runtime);
        }
      }
    });
  }
  ~Stdin() {
    g_stop = true;
    if (thread_.joinable()) thread_.join();
  }

 private:
  std::thread thread_;
};

struct Config {
  std::string role;
  std::vector<std::string> channels;
  std::vector<std::string> also;  // pub --type pose: more channels, each message on every one
  std::string type = "pose";
  std::string id = "P";
  std::string node = "peer";
  int nodes = 1;            // sub: nodes, each subscribing to every channel
  long count = 10;
  double rate = 100;
  std::size_t size = 1024;
  int width = 1920, height = 1080;
  int subscribers = 0;
  int publishers = 0;
  long expect = 0;
  long timeout_ms = 30000;
  bool local_sub = false;
  bool hold = false;
  std::size_t queue_depth = 16;
  std::uint32_t shm_slots = 8;
  std::uint32_t history = 0;  // pub: PublisherOptions::history (keep last N)
  std::size_t initial_slot = 4096;
  int topics = 1;
};

// What one subscriber saw.
struct Recorder {
  struct Source {
    std::int64_t last = -1;
    std::set<std::int64_t> seen;
    std::uint64_t received = 0, duplicates = 0, out_of_order = 0, gaps = 0;
  };
  std::mutex mu;
  std::map<std::string, Source> sources;
  std::uint64_t received = 0, bad_content = 0;
  std::int64_t first = -1, last = -1, min = -1;
  std::int64_t first_gap = -1;  // first sequence number missing (any source), -1 if none

  void on(const std::string& source, std::int64_t seq, bool content_ok) {
    std::lock_guard lock(mu);
    ++received;
    if (!content_ok) ++bad_content;
    if (first < 0) first = seq;
    last = seq;
    if (min < 0 || seq < min) min = seq;
    auto& s = sources[source];
    ++s.received;
    if (!s.seen.insert(seq).second) {
      ++s.duplicates;
      // LCMX_PEER_DUP_TRACE=1: which message came twice (in a test's output, to debug).
      if (std::getenv("LCMX_PEER_DUP_TRACE")) std::fprintf(stderr, "DUP %lld\n", static_cast<long long>(seq));
    }
    else if (s.last >= 0 && seq < s.last) ++s.out_of_order;
    else if (s.last >= 0 && seq > s.last + 1) {
      s.gaps += static_cast<std::uint64_t>(seq - s.last - 1);
      if (first_gap < 0) first_gap = s.last + 1;
    }
    if (seq > s.last) s.last = seq;
  }
  std::uint64_t count() {
    std::lock_guard lock(mu);
    return received;
  }
};

struct Channel {
  std::string name;
  std::string label;  // in SUMMARY lines: name, or name@<node index> with --nodes > 1
  Recorder rec;
  std::function<lcmx::SubscriberStats()> stats;
};

void summary(Channel& c) {
  const auto st = c.stats();
  std::string paths;
  for (const auto& p : st.publishers) {
    const std::string s = lcmx::to_string(p.path);
    if (paths.find(s) == std::string::npos) paths += (paths.empty() ? "" : ",") + s;
  }
  std::uint64_t dups = 0, ooo = 0, gaps = 0;
  std::string sources;
  {
    std::lock_guard lock(c.rec.mu);
    for (const auto& [id, s] : c.rec.sources) {
      dups += s.duplicates;
      ooo += s.out_of_order;
      gaps += s.gaps;
      sources += (sources.empty() ? "" : ",") + id + ":" + std::to_string(s.received);
    }
  }
  std::lock_guard lock(c.rec.mu);
  say("SUMMARY channel=" + (c.label.empty() ? c.name : c.label) + " received=" + std::to_string(c.rec.received) +
      " first=" + std::to_string(c.rec.first) + " last=" + std::to_string(c.rec.last) +
      " min=" + std::to_string(c.rec.min) +
      " duplicates=" + std::to_string(dups) + " out_of_order=" + std::to_string(ooo) +
      " gaps=" + std::to_string(gaps) + " first_gap=" + std::to_string(c.rec.first_gap) + " drops=" + std::to_string(st.drops) +
      " decode_errors=" + std::to_string(st.decode_errors) +
      " bad_content=" + std::to_string(c.rec.bad_content) +
      " publishers=" + std::to_string(st.publishers.size()) + " paths=" + (paths.empty() ? "-" : paths) +
      " sources=" + (sources.empty() ? "-" : sources) + " errors=" + std::to_string(st.errors.size()));
  for (const auto& e : st.errors) say("ERROR " + e);
}

// Subscribes to `channel` with the configured type; the callback records into c.rec.
template <class Sub>
void keep(std::vector<std::shared_ptr<void>>& keep_alive, Sub&& s, Channel& c) {
  auto p = std::make_shared<Sub>(std::forward<Sub>(s));
  c.stats = [p] { return p->stats(); };
  keep_alive.push_back(p);
}

void subscribe(lcmx::Node& node, const Config& cfg, Channel& c,
               std::vector<std::shared_ptr<void>>& keep_alive) {
  lcmx::SubscriberOptions so;
  so.queue_depth = cfg.queue_depth;
  auto* rec = &c.rec;
  if (cfg.type == "pose") {
    keep(keep_alive,
         node.subscribe<lcmx_examples::pose_t>(
             c.name,
             [rec](const lcmx_examples::pose_t& m) {
               const bool ok = m.position[0] == static_cast<double>(m.header.seq) && m.orientation[3] == 1.0;
               rec->on(m.header.frame_id, m.header.seq, ok);
             },
             so),
         c);
  } else if (cfg.type == "image") {
    keep(keep_alive,
         node.subscribe<lcmx_examples::image_t>(
             c.name,
             [rec](const lcmx_examples::image_t& m) {
               const bool ok = m.size == static_cast<std::int32_t>(m.data.size()) &&
                               m.size == m.stride * m.height && m.stride == m.width * 3 &&
                               m.encoding == "rgb8" && check(m.data, m.header.seq);
               rec->on(m.header.frame_id, m.header.seq, ok);
             },
             so),
         c);
  } else if (cfg.type == "bench") {
    keep(keep_alive,
         node.subscribe<lcmx_examples::bench_t>(
             c.name,
             [rec](const lcmx_examples::bench_t& m) {
               // data[0..7]: publisher id (NUL padded), then the pattern.
               std::string id;
               for (std::size_t i = 0; i < 8 && i < m.data.size() && m.data[i] != 0; ++i)
                 id.push_back(static_cast<char>(m.data[i]));
               const bool ok = m.size == static_cast<std::int32_t>(m.data.size()) && check(m.data, m.seq, 8);
               rec->on(id, m.seq, ok);
             },
             so),
         c);
  } else {
    throw std::invalid_argument("unknown --type " + cfg.type);
  }
}

bool deadline_passed(Clock::time_point deadline) { return Clock::now() >= deadline; }

int run_sub(const Config& cfg, lcmx::Runtime& rt, Stdin& in, Clock::time_point deadline) {
  std::vector<lcmx::Node> nodes;
  for (int k = 0; k < std::max(cfg.nodes, 1); ++k)
    nodes.push_back(rt.create_node(k == 0 ? cfg.node : cfg.node + std::to_string(k)));
  std::vector<std::unique_ptr<Channel>> chans;
  std::vector<std::shared_ptr<void>> keep_alive;
  for (std::size_t k = 0; k < nodes.size(); ++k)
    for (const auto& name : cfg.channels) {
      chans.push_back(std::make_unique<Channel>());
      chans.back()->name = name;
      if (k > 0) chans.back()->label = name + "@" + std::to_string(k);
      subscribe(nodes[k], cfg, *chans.back(), keep_alive);
    }
  say("READY");
  if (cfg.publishers > 0) {
    for (auto& c : chans) {
      while (c->stats().publishers.size() < static_cast<std::size_t>(cfg.publishers)) {
        if (deadline_passed(deadline) || g_quit) {
          say("TIMEOUT waiting for publishers on " + c->name);
          return 3;
        }
        std::this_thread::sleep_for(5ms);  // polling a condition with a deadline
      }
    }
    say("MATCHED");
  }
  int rc = 0;
  for (;;) {
    if (in.status_requests.load() > 0) {
      --in.status_requests;
      for (auto& c : chans) summary(*c);
      say("END");
    }
    if (g_quit) break;
    if (cfg.expect > 0) {
      bool all = true;
      for (auto& c : chans) all = all && c->rec.count() >= static_cast<std::uint64_t>(cfg.expect);
      if (all) break;
    }
    if (deadline_passed(deadline)) {
      say("TIMEOUT");
      rc = 3;
      break;
    }
    std::this_thread::sleep_for(2ms);
  }
  for (auto& c : chans) summary(*c);
  say("END");
  return rc;
}

void set_id(std::vector<std::uint8_t>& data, const std::string& id) {
  for (std::size_t i = 0; i < 8 && i < data.size(); ++i) data[i] = i < id.size() ? static_cast<std::uint8_t>(id[i]) : 0;
}

int run_pub(const Config& cfg, lcmx::Runtime& rt, Stdin& in, Clock::time_point deadline) {
  auto node = rt.create_node(cfg.node);
  lcmx::PublisherOptions po;
  po.shm_slots = cfg.shm_slots;
  po.history = cfg.history;
  po.shm_initial_slot_size = cfg.initial_slot;
  po.max_message_size = std::max<std::size_t>(16u << 20, cfg.size + 4096);
  const std::string& channel = cfg.channels.at(0);

  std::optional<lcmx::Node> local_node;
  std::vector<std::shared_ptr<void>> keep_alive;
  Channel local;
  local.name = channel;
  if (cfg.local_sub) {
    local_node.emplace(rt.create_node(cfg.node + "_local"));
    subscribe(*local_node, cfg, local, keep_alive);
  }

  std::function<void(std::int64_t)> publish;
  std::function<bool(std::size_t, std::chrono::milliseconds)> wait_subs;
  std::function<std::uint64_t()> published;
  lcmx::Publisher<lcmx_examples::pose_t> pose_pub;
  lcmx::Publisher<lcmx_examples::image_t> image_pub;
  lcmx::Publisher<lcmx_examples::bench_t> bench_pub;
  lcmx_examples::pose_t pose{};
  lcmx_examples::image_t image{};
  lcmx_examples::bench_t bench{};
  std::vector<lcmx::Publisher<lcmx_examples::pose_t>> also_pubs;  // --also: one socket, several channels
  if (cfg.type == "pose") {
    pose_pub = node.advertise<lcmx_examples::pose_t>(channel, po);
    for (const auto& c : cfg.also) also_pubs.push_back(node.advertise<lcmx_examples::pose_t>(c, po));
    pose.header.frame_id = cfg.id;
    pose.orientation[3] = 1.0;
    publish = [&](std::int64_t seq) {
      pose.header.seq = seq;
      pose.header.stamp_ns = now_ns();
      pose.position[0] = static_cast<double>(seq);
      pose_pub.publish(pose);
      for (auto& p : also_pubs) p.publish(pose);
    };
    wait_subs = [&](std::size_t n, std::chrono::milliseconds t) {
      if (!pose_pub.wait_for_subscribers(n, t)) return false;
      for (auto& p : also_pubs)
        if (!p.wait_for_subscribers(n, t)) return false;
      return true;
    };
    published = [&] { return pose_pub.published(); };
  } else if (cfg.type == "image") {
    image_pub = node.advertise<lcmx_examples::image_t>(channel, po);
    image.header.frame_id = cfg.id;
    image.width = cfg.width;
    image.height = cfg.height;
    image.stride = cfg.width * 3;
    image.encoding = "rgb8";
    image.size = image.stride * image.height;
    image.data.resize(static_cast<std::size_t>(image.size));
    publish = [&](std::int64_t seq) {
      image.header.seq = seq;
      image.header.stamp_ns = now_ns();
      fill(image.data, seq);
      image_pub.publish(image);
    };
    wait_subs = [&](std::size_t n, std::chrono::milliseconds t) { return image_pub.wait_for_subscribers(n, t); };
    published = [&] { return image_pub.published(); };
  } else if (cfg.type == "bench") {
    bench_pub = node.advertise<lcmx_examples::bench_t>(channel, po);
    bench.size = static_cast<std::int32_t>(std::max<std::size_t>(cfg.size, 8));
    bench.data.resize(static_cast<std::size_t>(bench.size));
    publish = [&](std::int64_t seq) {
      bench.seq = seq;
      bench.send_ns = now_ns();
      fill(bench.data, seq);
      set_id(bench.data, cfg.id);
      bench_pub.publish(bench);
    };
    wait_subs = [&](std::size_t n, std::chrono::milliseconds t) { return bench_pub.wait_for_subscribers(n, t); };
    published = [&] { return bench_pub.published(); };
  } else {
    throw std::invalid_argument("unknown --type " + cfg.type);
  }
  say("READY");
  if (cfg.subscribers > 0) {
    const std::size_t want = static_cast<std::size_t>(cfg.subscribers) + (cfg.local_sub ? 1 : 0);
    while (!wait_subs(want, 50ms)) {
      if (deadline_passed(deadline) || g_quit) {
        say("TIMEOUT waiting for subscribers");
        return 3;
      }
    }
    say("MATCHED " + std::to_string(want));
  }
  const auto period = cfg.rate > 0 ? std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(1.0 / cfg.rate))
                                   : Clock::duration::zero();
  auto next = Clock::now();
  for (std::int64_t seq = 0; cfg.count == 0 || seq < cfg.count; ++seq) {
    if (g_quit) break;
    if (deadline_passed(deadline)) {
      say("TIMEOUT publishing");
      return 3;
    }
    if (in.status_requests.load() > 0) {
      --in.status_requests;
      say("STATUS published=" + std::to_string(published()));
    }
    publish(seq);
    if (period > Clock::duration::zero()) {
      next += period;
      std::this_thread::sleep_until(next);  // pacing the rate, not synchronisation
    }
  }
  say("PUBLISHED " + std::to_string(published()));
  if (cfg.hold) {
    while (!g_quit) {
      if (deadline_passed(deadline)) {
        say("TIMEOUT holding");
        return 3;
      }
      if (in.status_requests.load() > 0) {
        --in.status_requests;
        if (local.stats) summary(local);
        say("STATUS published=" + std::to_string(published()));
      }
      std::this_thread::sleep_for(5ms);
    }
  }
  if (local.stats) {
    summary(local);
    say("END");
  }
  return 0;
}

int run_idle(const Config& cfg, lcmx::Runtime& rt, Stdin& in, Clock::time_point deadline) {
  (void)in;
  // A publisher that does not publish, held until "quit".
  auto node = rt.create_node(cfg.node);
  lcmx::Publisher<lcmx_examples::pose_t> pub;
  if (!cfg.channels.empty()) pub = node.advertise<lcmx_examples::pose_t>(cfg.channels.at(0));
  say("READY");
  while (!g_quit) {
    if (deadline_passed(deadline)) return 3;
    std::this_thread::sleep_for(5ms);
  }
  return 0;
}

// Raw publishers on `--topics` channels "<channel>_<k>": waits (deadline) until each has a
// subscriber, prints "MATCHED", publishes --count rounds (one message per channel each: the
// round number as 8 bytes), prints "PUBLISHED <n>", then waits for "quit".
int run_many(const Config& cfg, lcmx::Runtime& rt, Clock::time_point deadline) {
  auto node = rt.create_node(cfg.node);
  std::vector<lcmx::RawPublisher> pubs;
  for (int k = 0; k < cfg.topics; ++k)
    pubs.push_back(node.advertise_raw(cfg.channels.at(0) + "_" + std::to_string(k)));
  say("READY");
  for (auto& p : pubs)
    while (!p.wait_for_subscribers(1, 50ms))
      if (deadline_passed(deadline) || g_quit) {
        say("TIMEOUT waiting for subscribers on " + p.channel());
        return 3;
      }
  say("MATCHED " + std::to_string(pubs.size()));
  std::uint64_t n = 0;
  for (std::int64_t round = 0; round < cfg.count; ++round)
    for (auto& p : pubs) {
      std::byte data[8];
      std::memcpy(data, &round, sizeof data);
      p.publish(data);
      ++n;
    }
  say("PUBLISHED " + std::to_string(n));
  while (!g_quit) {
    if (deadline_passed(deadline)) return 3;
    std::this_thread::sleep_for(5ms);
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"lcmx_test_peer: a participant for lcmx's integration tests"};
  Config cfg;
  app.add_option("role", cfg.role, "pub | sub | idle | many")->required()->check(CLI::IsMember({"pub", "sub", "idle", "many"}));
  app.add_option("--topics", cfg.topics, "many: raw publishers on <channel>_0 .. <channel>_<topics-1>");
  app.add_option("--channel", cfg.channels, "channel (sub: may repeat)");
  app.add_option("--also", cfg.also, "pub --type pose: another channel, each message published on it too (may repeat)");
  app.add_option("--type", cfg.type, "pose | image | bench")->check(CLI::IsMember({"pose", "image", "bench"}));
  app.add_option("--id", cfg.id, "publisher tag carried in every message");
  app.add_option("--node", cfg.node, "node name");
  app.add_option("--nodes", cfg.nodes, "sub: this many nodes, each subscribing to every channel (summaries of node k > 0 as channel@k)");
  app.add_option("--count", cfg.count, "messages to publish (0: until killed or quit)");
  app.add_option("--rate", cfg.rate, "publish rate in Hz (0: as fast as possible)");
  app.add_option("--size", cfg.size, "bench: payload bytes");
  app.add_option("--width", cfg.width, "image width");
  app.add_option("--height", cfg.height, "image height");
  app.add_option("--subscribers", cfg.subscribers, "pub: wait for this many remote subscribers");
  app.add_option("--publishers", cfg.publishers, "sub: wait for this many publishers per channel");
  app.add_option("--expect", cfg.expect, "sub: exit after this many messages per channel");
  app.add_option("--timeout-ms", cfg.timeout_ms, "give up (exit 3) after this long");
  app.add_option("--queue-depth", cfg.queue_depth, "sub: intra-process queue depth");
  app.add_option("--shm-slots", cfg.shm_slots, "pub: shared-memory ring depth");
  app.add_option("--history", cfg.history, "pub: keep last N for subscribers that match later");
  app.add_option("--initial-slot", cfg.initial_slot, "pub: first shared-memory slot size in bytes");
  app.add_flag("--local-sub", cfg.local_sub, "pub: also subscribe in this process (intra path)");
  app.add_flag("--hold", cfg.hold, "pub: after publishing, wait for quit");
  CLI11_PARSE(app, argc, argv);
  if (cfg.channels.empty() && cfg.role != "idle") {
    std::cerr << "lcmx_test_peer: --channel is required\n";
    return 2;
  }
  struct sigaction sa {};
  sa.sa_handler = [](int) { g_quit = true; };
  sigaction(SIGTERM, &sa, nullptr);
  sigaction(SIGINT, &sa, nullptr);
  const auto deadline = Clock::now() + std::chrono::milliseconds(cfg.timeout_ms);
  try {
    auto rt = lcmx::Runtime::create();
    rt.on_event([](const lcmx::Event& e) {
      say(std::string("EVENT ") + lcmx::to_string(e.kind) + " " + (e.channel.empty() ? "-" : e.channel) + " " + e.message);
    });
    Stdin in;
    in.runtime = &rt;
    in.start();
    int rc = 0;
    if (cfg.role == "pub") rc = run_pub(cfg, rt, in, deadline);
    else if (cfg.role == "sub") rc = run_sub(cfg, rt, in, deadline);
    else if (cfg.role == "many") rc = run_many(cfg, rt, deadline);
    else rc = run_idle(cfg, rt, in, deadline);
    rt.on_event(nullptr);
    return rc;
  } catch (const std::exception& e) {
    say(std::string("FATAL ") + e.what());
    return 1;
  }
}
