// lcmx_bench_soak: the demo's traffic for a long time while random processes are killed and
// restarted (issue 10's soak). Not a CI test: it runs for minutes (default 10).
//
// Processes (children of this orchestrator, all in one private network namespace it creates,
// so every packet stays inside it):
//   image-pub  RawPublisher "SOAK_IMAGE": --image-size bytes at --image-hz (default 6.2 MB, 30 Hz)
//   small-pub  --small-topics RawPublishers "SOAK_S000".. at --small-hz (default 100 x 100 Hz)
//   sub-0..N-1 a RawSubscriber on every channel; sub-0 is never killed (the survivor whose
//              RSS is watched)
// Every --kill-every-ms a random process other than sub-0 gets SIGKILL (or --signal) and is
// started again at once.
//
// Every message carries {magic, incarnation, seq, size} and a body filled with one 8-byte word
// derived from (incarnation, seq). Subscribers check per channel and publisher incarnation:
//   gap        seq > last + 1: (seq - last - 1) messages missed
//   duplicate  seq <= last
//   torn       a body word (start, middle, end) that does not match the header
// and read lcmx's own counted drops per channel (SubscriberStats::drops). Messages missed that
// lcmx did not count: uncounted = sum over channels of max(0, gaps - drops). Messages published
// before a subscriber matched a (new) publisher are not a gap: counting starts at the first
// message received from each publisher incarnation.
// At the end every child is stopped with SIGTERM (clean exit), then /dev/shm is searched for
// segments of this run (host id LCMX_HOST_ID set per run) that nobody removed.
#include <fcntl.h>
#include <poll.h>
#include <sched.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cinttypes>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <dirent.h>
#include <fstream>
#include <map>
#include <random>
#include <sstream>
#include <string>
#include <unordered_map>
#include <vector>

#include "harness/options.hpp"
#include "harness/process.hpp"
#include "harness/report.hpp"
#include "lcmx/core.hpp"

namespace lcmxbench {
namespace {

constexpr std::uint64_t kMagic = 0x4c434d58534f414bull;  // "LCMXSOAK"

struct Header {
  std::uint64_t magic;
  std::uint64_t incarnation;
  std::uint64_t seq;
  std::uint64_t size;
};
static_assert(sizeof(Header) == 32);

std::uint64_t body_word(std::uint64_t inc, std::uint64_t seq) {
  return (inc * 0x9e3779b97f4a7c15ull) ^ (seq + 0x5bd1e995ull);
}

struct Settings {
  int duration_s = 600;
  int kill_every_ms = 3000;
  int subs = 3;
  std::size_t image_size = 6'200'000;
  int image_hz = 30;
  int small_topics = 100;
  int small_hz = 100;
  std::size_t small_size = 256;
  unsigned seed = 1;
  std::string signal = "KILL";
  std::string url = "udpm://239.255.77.231:17731?ttl=0";
  std::string markdown;
};

std::string small_channel(int i) {
  char b[32];
  std::snprintf(b, sizeof b, "SOAK_S%03d", i);
  return b;
}

lcmx::RuntimeOptions child_options(const std::string& url) {
  auto o = lcmx::RuntimeOptions::from_env();  // LCMX_HOST_ID etc. from the orchestrator
  o.discovery_url = url;
  return o;
}

// Blocks SIGTERM/SIGINT in this thread (and the threads lcmx starts later), so the role can
// poll for them with sigtimedwait.
sigset_t block_stop_signals() {
  sigset_t s;
  sigemptyset(&s);
  sigaddset(&s, SIGTERM);
  sigaddset(&s, SIGINT);
  pthread_sigmask(SIG_BLOCK, &s, nullptr);
  return s;
}

bool stop_requested(const sigset_t& s, int wait_ms) {
  timespec ts{wait_ms / 1000, (wait_ms % 1000) * 1'000'000L};
  return ::sigtimedwait(&s, nullptr, &ts) > 0;
}

std::uint64_t new_incarnation() {
  std::random_device rd;
  return (static_cast<std::uint64_t>(rd()) << 32) ^ rd() ^ static_cast<std::uint64_t>(::getpid());
}

void fill(std::byte* p, std::size_t size, std::uint64_t inc, std::uint64_t seq) {
  Header h{kMagic, inc, seq, size};
  std::memcpy(p, &h, sizeof h);
  const std::uint64_t w = body_word(inc, seq);
  const std::size_t words = (size - sizeof h) / 8;
  auto* q = p + sizeof h;
  for (std::size_t i = 0; i < words; ++i) std::memcpy(q + i * 8, &w, 8);
}

// ---- publishers ----

int run_pub(const Settings& s, bool image) {
  const sigset_t sigs = block_stop_signals();
  try {
    auto rt = lcmx::Runtime::create(child_options(s.url));
    auto node = rt.create_node(image ? "soak_image_pub" : "soak_small_pub");
    const std::uint64_t inc = new_incarnation();
    std::vector<lcmx::RawPublisher> pubs;
    lcmx::PublisherOptions po;  // defaults
    if (image) {
      pubs.push_back(node.advertise_raw("SOAK_IMAGE", po));
    } else {
      for (int i = 0; i < s.small_topics; ++i) pubs.push_back(node.advertise_raw(small_channel(i), po));
    }
    const std::size_t size = image ? s.image_size : s.small_size;
    const int hz = image ? s.image_hz : s.small_hz;
    std::vector<std::byte> buf(size);
    report_line("ready");
    std::uint64_t seq = 0, published = 0;
    timespec next{};
    ::clock_gettime(CLOCK_MONOTONIC, &next);
    const long period_ns = 1'000'000'000L / hz;
    std::int64_t last_report = now_ns();
    for (;;) {
      for (auto& p : pubs) {
        if (image) {
          auto loan = p.loan(size);
          fill(loan.data(), size, inc, seq);
          p.publish(std::move(loan), size);
        } else {
          fill(buf.data(), size, inc, seq);
          p.publish(buf);
        }
        ++published;
      }
      ++seq;
      if (now_ns() - last_report > 1'000'000'000) {
        report_line("pub " + std::to_string(published));
        last_report = now_ns();
      }
      next.tv_nsec += period_ns;
      while (next.tv_nsec >= 1'000'000'000L) next.tv_nsec -= 1'000'000'000L, ++next.tv_sec;
      while (::clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, nullptr) == EINTR) {}
      if (stop_requested(sigs, 0)) break;
    }
    report_line("pub " + std::to_string(published));
    report_line("done");
  } catch (const std::exception& e) {
    report_error(std::string("publisher: ") + e.what());
    return 1;
  }
  return 0;
}

// ---- subscribers ----

struct ChannelCheck {
  struct Inc {
    std::uint64_t last = 0;
    std::int64_t seen_ns = 0;  // last message from this incarnation
  };
  std::uint64_t since_prune = 0;
  std::unordered_map<std::uint64_t, Inc> incs;  // executor thread only
  // Written by the executor thread, read by the reporting thread.
  std::atomic<std::uint64_t> received{0}, gaps{0}, dups{0}, torn{0}, malformed{0};

  void on(std::span<const std::byte> d) {
    Header h;
    if (d.size() < sizeof h) {
      ++malformed;
      return;
    }
    std::memcpy(&h, d.data(), sizeof h);
    if (h.magic != kMagic || h.size != d.size()) {
      ++malformed;
      return;
    }
    ++received;
    const std::uint64_t w = body_word(h.incarnation, h.seq);
    const std::size_t words = (d.size() - sizeof h) / 8;
    if (words > 0) {
      for (std::size_t i : {std::size_t{0}, words / 2, words - 1}) {
        std::uint64_t got;
        std::memcpy(&got, d.data() + sizeof h + i * 8, 8);
        if (got != w) {
          ++torn;
          break;
        }
      }
    }
    // Forget publisher incarnations silent for 10 s (killed ones), so this bookkeeping does not
    // grow with every restart and the survivor's RSS shows lcmx's memory, not the bench's.
    const std::int64_t now = now_ns();
    if (++since_prune >= 1000) {
      since_prune = 0;
      std::erase_if(incs, [now](const auto& kv) { return now - kv.second.seen_ns > 10'000'000'000LL; });
    }
    auto [it, fresh] = incs.try_emplace(h.incarnation);
    it->second.seen_ns = now;
    if (fresh) {
      it->second.last = h.seq;
      return;
    }
    if (h.seq <= it->second.last) {
      ++dups;
      return;
    }
    gaps += h.seq - it->second.last - 1;
    it->second.last = h.seq;
  }
};

int run_sub(const Settings& s, int index) {
  const sigset_t sigs = block_stop_signals();
  try {
    auto rt = lcmx::Runtime::create(child_options(s.url));
    auto node = rt.create_node("soak_sub_" + std::to_string(index));
    const int n = 1 + s.small_topics;
    std::vector<ChannelCheck> checks(static_cast<std::size_t>(n));
    std::vector<lcmx::RawSubscriber> subs;
    for (int i = 0; i < n; ++i) {
      const std::string ch = i == 0 ? std::string("SOAK_IMAGE") : small_channel(i - 1);
      subs.push_back(node.subscribe_raw(ch, [&checks, i](const lcmx::RawMessage& m) {
        checks[static_cast<std::size_t>(i)].on(m.data);  // one executor thread per node
      }));
    }
    report_line("ready");
    auto report = [&] {
      // lcmx counts a drop before it delivers the message after it, which reveals the gap:
      // so gaps are read first and drops after, and every gap read has its drop read too.
      std::uint64_t recv = 0, gaps = 0, dups = 0, torn = 0, bad = 0, drops = 0, uncounted = 0;
      for (int i = 0; i < n; ++i) {
        const auto& c = checks[static_cast<std::size_t>(i)];
        const std::uint64_t g = c.gaps.load();
        const auto st = subs[static_cast<std::size_t>(i)].stats();
        recv += c.received.load(), gaps += g, dups += c.dups.load(), torn += c.torn.load(),
            bad += c.malformed.load();
        drops += st.drops;
        if (g > st.drops) uncounted += g - st.drops;
      }
      char line[256];
      std::snprintf(line, sizeof line,
                    "rep %" PRIu64 " %" PRIu64 " %" PRIu64 " %" PRIu64 " %" PRIu64 " %" PRIu64 " %" PRIu64,
                    recv, gaps, dups, torn, bad, drops, uncounted);
      report_line(line);
    };
    while (!stop_requested(sigs, 500)) report();
    report();
    report_line("done");
  } catch (const std::exception& e) {
    report_error(std::string("subscriber: ") + e.what());
    return 1;
  }
  return 0;
}

// ---- orchestrator ----

struct Child {
  explicit Child(std::string r) : role(std::move(r)) {}
  std::string role;  // image-pub | small-pub | sub-K
  pid_t pid = -1;
  std::unique_ptr<Pipe> pipe;
  LineReader reader;
  int restarts = 0;
};

struct Totals {
  std::uint64_t recv = 0, gaps = 0, dups = 0, torn = 0, bad = 0, drops = 0, uncounted = 0;
  std::uint64_t published = 0;
  int errors = 0;
  std::vector<std::string> error_lines;
};

// Folds one child's lines into the totals: the last "rep"/"pub" line of an incarnation is its
// final word (a killed incarnation's last report is at most 0.5 s old).
void fold(const Child& c, Totals& t) {
  const std::string* last_rep = nullptr;
  const std::string* last_pub = nullptr;
  for (const auto& l : c.reader.lines) {
    if (l.rfind("rep ", 0) == 0) last_rep = &l;
    else if (l.rfind("pub ", 0) == 0) last_pub = &l;
    else if (l.rfind("error", 0) == 0) {
      ++t.errors;
      t.error_lines.push_back(c.role + ": " + l);
    }
  }
  if (last_rep) {
    std::uint64_t v[7] = {};
    std::sscanf(last_rep->c_str(), "rep %" SCNu64 " %" SCNu64 " %" SCNu64 " %" SCNu64 " %" SCNu64 " %" SCNu64 " %" SCNu64,
                &v[0], &v[1], &v[2], &v[3], &v[4], &v[5], &v[6]);
    t.recv += v[0], t.gaps += v[1], t.dups += v[2], t.torn += v[3], t.bad += v[4], t.drops += v[5],
        t.uncounted += v[6];
  }
  if (last_pub) t.published += std::strtoull(last_pub->c_str() + 4, nullptr, 10);
}

// Waits up to `timeout_ms` for a signalled child to exit and returns its wait status. A child
// still there is hung: its threads' stacks are printed (gdb, when installed), so the hang can be
// diagnosed from the bench's output, then it is SIGKILLed (*killed = true).
int wait_or_dump(const Child& c, int timeout_ms, bool* killed) {
  int st = 0;
  *killed = false;
  const std::int64_t deadline = now_ns() + static_cast<std::int64_t>(timeout_ms) * 1'000'000;
  pid_t r = 0;
  while ((r = ::waitpid(c.pid, &st, WNOHANG)) == 0 && now_ns() < deadline)
    ::usleep(10'000);  // polling a child with a deadline
  if (r != 0) return st;
  std::fprintf(stderr, "\nsoak: %s (pid %d) did not exit within %d ms; its stacks:\n", c.role.c_str(), c.pid,
               timeout_ms);
  const std::string cmd = "gdb -p " + std::to_string(c.pid) +
                          " -batch -ex 'thread apply all bt' 2>/dev/null | grep -E '^(#|Thread)' >&2";
  if (std::system(cmd.c_str()) != 0) std::fprintf(stderr, "soak: (no gdb: no stacks)\n");
  std::atomic<int> never{0};
  return reap_child(c.pid, 0, never, killed);
}

// A process's resident memory (KB) from /proc/<pid>/status, split as the kernel does: anon
// (heap, stacks: what a leak grows), file (mapped binaries) and shmem (touched pages of the
// shared-memory segments it maps: these follow which publishers are alive, not leaks).
struct Rss {
  long total = -1, anon = -1, file = -1, shmem = -1;
};
Rss rss_kb(pid_t pid) {
  std::ifstream f("/proc/" + std::to_string(pid) + "/status");
  std::string line;
  Rss r;
  auto field = [&](const char* key, long& out) {
    if (line.rfind(key, 0) == 0) out = std::strtol(line.c_str() + std::strlen(key), nullptr, 10);
  };
  while (std::getline(f, line)) {
    field("VmRSS:", r.total);
    field("RssAnon:", r.anon);
    field("RssFile:", r.file);
    field("RssShmem:", r.shmem);
  }
  return r;
}

// Least-squares slope of y over x (x in seconds): KB per minute.
double slope_kb_per_min(const std::vector<std::pair<double, double>>& xy) {
  if (xy.size() < 2) return 0.0;
  double sx = 0, sy = 0, sxx = 0, sxy = 0;
  for (const auto& [x, y] : xy) sx += x, sy += y, sxx += x * x, sxy += x * y;
  const double n = static_cast<double>(xy.size());
  const double den = n * sxx - sx * sx;
  return den == 0.0 ? 0.0 : 60.0 * (n * sxy - sx * sy) / den;
}

std::vector<std::string> shm_files_with(const std::string& needle) {
  std::vector<std::string> out;
  if (DIR* d = ::opendir("/dev/shm")) {
    while (auto* e = ::readdir(d))
      if (std::strstr(e->d_name, needle.c_str())) out.emplace_back(e->d_name);
    ::closedir(d);
  }
  return out;
}

int signal_number(const std::string& name) {
  if (name == "KILL") return SIGKILL;
  if (name == "TERM") return SIGTERM;
  if (name == "INT") return SIGINT;
  return -1;
}

int orchestrate(const Settings& s, const std::string& self) {
  const int sig = signal_number(s.signal);
  if (sig < 0) {
    std::fprintf(stderr, "lcmx_bench_soak: --signal must be KILL, TERM or INT\n");
    return 2;
  }
  // A private network namespace: every packet of the run stays in it; it disappears with the
  // last process of the run, even after SIGKILL.
  if (::unshare(CLONE_NEWNET) != 0) {
    std::fprintf(stderr, "lcmx_bench_soak: unshare(CLONE_NEWNET): %s (needs root)\n", std::strerror(errno));
    return 1;
  }
  if (std::system("ip link set lo up && ip route add 224.0.0.0/4 dev lo") != 0) {
    std::fprintf(stderr, "lcmx_bench_soak: could not bring lo up in the private namespace\n");
    return 1;
  }
  char host_hex[32];
  const std::uint64_t host = 0x5a0c000000000000ull | (static_cast<std::uint64_t>(::getpid()) & 0xffffffull);
  std::snprintf(host_hex, sizeof host_hex, "%" PRIx64, host);
  ::setenv("LCMX_HOST_ID", (std::string("0x") + host_hex).c_str(), 1);
  on_stop_signals(OnStop::flag);  // the run stops its children itself (SIGTERM, final reports)

  auto common_args = [&](const std::string& role) {
    return std::vector<std::string>{self, "--role", role, "--url", s.url,
                                    "--image-size", std::to_string(s.image_size),
                                    "--image-hz", std::to_string(s.image_hz),
                                    "--small-topics", std::to_string(s.small_topics),
                                    "--small-hz", std::to_string(s.small_hz),
                                    "--small-size", std::to_string(s.small_size)};
  };
  std::vector<Child> live;
  live.reserve(static_cast<std::size_t>(2 + s.subs));
  std::vector<Child> finished;  // ended incarnations, with their lines
  auto start = [&](Child& c) {
    c.pipe = std::make_unique<Pipe>();
    c.reader = LineReader{};
    c.reader.fd = c.pipe->r;
    c.pid = spawn_child(common_args(c.role), {c.pipe->w}, -1);
    c.pipe->close_w();
    ::fcntl(c.pipe->r, F_SETFL, O_NONBLOCK);
  };
  for (int k = 0; k < s.subs; ++k) live.push_back(Child("sub-" + std::to_string(k)));
  live.push_back(Child("image-pub"));
  live.push_back(Child("small-pub"));
  for (auto& c : live) start(c);

  auto pump_all = [&](int ms) {
    std::vector<LineReader*> rs;
    for (auto& c : live) rs.push_back(&c.reader);
    const std::int64_t deadline = now_ns() + static_cast<std::int64_t>(ms) * 1'000'000;
    pump_until(rs, deadline, [] { return false; });
  };

  std::mt19937 rng(s.seed);
  std::map<std::string, int> kills;
  const std::int64_t t0 = now_ns();
  const std::int64_t end = t0 + static_cast<std::int64_t>(s.duration_s) * 1'000'000'000;
  const std::int64_t rss_at = t0 + static_cast<std::int64_t>(s.duration_s) * 250'000'000;  // 25 %
  Rss rss_first, rss_last;
  long rss_max = -1;
  std::vector<std::pair<double, double>> anon_samples;  // (s since 25 %, RssAnon KB)
  std::int64_t next_rss_sample = rss_at;
  std::int64_t next_kill = t0 + static_cast<std::int64_t>(s.kill_every_ms) * 1'000'000;
  std::int64_t next_progress = t0;
  bool ok = true;
  while (!stopped() && now_ns() < end) {
    pump_all(100);
    const std::int64_t now = now_ns();
    if (now >= next_rss_sample) {
      const Rss r = rss_kb(live[0].pid);  // sub-0, the survivor
      if (rss_first.total < 0) rss_first = r;
      rss_last = r;
      rss_max = std::max(rss_max, r.total);
      anon_samples.emplace_back(static_cast<double>(now - rss_at) / 1e9, static_cast<double>(r.anon));
      next_rss_sample = now + 1'000'000'000;
    }
    // A child that died by itself is a failure of the run (restart it, but say so).
    for (auto& c : live) {
      int st = 0;
      if (::waitpid(c.pid, &st, WNOHANG) == c.pid) {
        std::fprintf(stderr, "soak: %s (pid %d) exited by itself (status %d); restarted\n", c.role.c_str(),
                     c.pid, st);
        ok = false;
        c.reader.pump();
        finished.push_back(std::move(c));
        Child n(finished.back().role);
        n.restarts = finished.back().restarts + 1;
        c = std::move(n);
        start(c);
      }
    }
    if (now >= next_kill && s.kill_every_ms > 0) {
      std::uniform_int_distribution<std::size_t> pick(1, live.size() - 1);  // never sub-0
      Child& c = live[pick(rng)];
      ::kill(c.pid, sig);
      bool hung = false;
      wait_or_dump(c, 10'000, &hung);
      if (hung && sig != SIGKILL) ok = false;  // a clean stop signal must end a child
      for (int i = 0; i < 50 && !c.reader.eof; ++i) c.reader.pump();
      ++kills[c.role];
      finished.push_back(std::move(c));
      Child n(finished.back().role);
      n.restarts = finished.back().restarts + 1;
      c = std::move(n);
      start(c);
      next_kill = now + static_cast<std::int64_t>(s.kill_every_ms) * 1'000'000;
    }
    if (now >= next_progress) {
      std::fprintf(stderr, "\rsoak: %3d / %d s, kills %d   ", static_cast<int>((now - t0) / 1'000'000'000),
                   s.duration_s, [&] {
                     int k = 0;
                     for (auto& [_, v] : kills) k += v;
                     return k;
                   }());
      next_progress = now + 5'000'000'000;
    }
  }
  std::fprintf(stderr, "\n");
  // Clean stop: SIGTERM, then the final reports. A child restarted just now may not have
  // blocked SIGTERM yet (its default action would kill it, not a fault of lcmx): wait for every
  // child's "ready" first (bounded).
  {
    std::vector<LineReader*> rs;
    for (auto& c : live) rs.push_back(&c.reader);
    std::atomic<int> never{0};
    pump_until(rs, now_ns() + 10'000'000'000LL, [&] {
      return std::all_of(live.begin(), live.end(), [](const Child& c) { return c.reader.has("ready"); });
    }, never);
  }
  for (auto& c : live) ::kill(c.pid, SIGTERM);
  {
    std::vector<LineReader*> rs;
    for (auto& c : live) rs.push_back(&c.reader);
    std::atomic<int> never{0};
    pump_until(rs, now_ns() + 20'000'000'000LL, [] { return false; }, never);
  }
  for (auto& c : live) {
    bool killed = false;
    std::atomic<int> never{0};
    const int st = wait_or_dump(c, 10'000, &killed);
    if (killed || !WIFEXITED(st) || WEXITSTATUS(st) != 0) {
      std::fprintf(stderr, "soak: %s (pid %d) did not exit cleanly on SIGTERM: %s %d\n", c.role.c_str(), c.pid,
                   killed ? "hung, SIGKILLed" : WIFSIGNALED(st) ? "killed by signal" : "exit status",
                   killed ? 0 : WIFSIGNALED(st) ? WTERMSIG(st) : WEXITSTATUS(st));
      ok = false;
    }
    finished.push_back(std::move(c));
  }
  // Segments are removed by their owners on a clean exit, and orphans of killed processes by
  // the next participants (start-up reclaim, leases). Give the last reclaim its lease.
  std::vector<std::string> left;
  const std::int64_t shm_deadline = now_ns() + 10'000'000'000LL;
  do {
    left = shm_files_with(host_hex);
    if (left.empty()) break;
    ::usleep(100'000);  // polling a directory with a deadline, not synchronising with a peer
  } while (now_ns() < shm_deadline);

  Totals t;
  for (const auto& c : finished) fold(c, t);
  // RssAnon's trend over the whole measured window and each half: a heap that settles shows
  // a first-half rise and a flat second half; a leak rises in both.
  const auto half = static_cast<std::ptrdiff_t>(anon_samples.size() / 2);
  auto kb_min = [](const std::vector<std::pair<double, double>>& xy) {
    char b[32];
    std::snprintf(b, sizeof b, "%+.1f KB/min", slope_kb_per_min(xy));
    return std::string(b);
  };
  int total_kills = 0;
  for (auto& [_, v] : kills) total_kills += v;

  std::ostringstream md;
  md << "## lcmx soak: " << s.duration_s << " s, a random process killed (SIG" << s.signal << ") every "
     << s.kill_every_ms << " ms\n\n"
     << "Traffic: " << s.image_size << " B at " << s.image_hz << " Hz on SOAK_IMAGE + " << s.small_topics
     << " topics x " << s.small_hz << " Hz x " << s.small_size << " B; " << s.subs
     << " subscriber processes (sub-0 never killed).\n\n"
     << "| figure | value | target |\n|---|---|---|\n"
     << "| processes killed and restarted | " << total_kills;
  for (auto& [k, v] : kills) md << " (" << k << ": " << v << ")";
  md << " | |\n"
     << "| messages published (last report of each publisher incarnation) | " << t.published << " | |\n"
     << "| messages received by subscribers | " << t.recv << " | |\n"
     << "| missed (gaps in seq) | " << t.gaps << " | |\n"
     << "| counted drops (SubscriberStats::drops) | " << t.drops << " | |\n"
     << "| **lost uncounted** (per channel max(0, gaps - drops)) | " << t.uncounted << " | 0 |\n"
     << "| **duplicates** | " << t.dups << " | 0 |\n"
     << "| **torn** (body does not match header) | " << t.torn << " | 0 |\n"
     << "| malformed (bad header/size) | " << t.bad << " | 0 |\n"
     << "| survivor RSS (sub-0, KB) at 25 % / end / max | " << rss_first.total << " / " << rss_last.total
     << " / " << rss_max << " | |\n"
     << "| survivor RssShmem (mapped segments' touched pages, KB) at 25 % / end | " << rss_first.shmem << " / "
     << rss_last.shmem << " | |\n"
     << "| survivor RssFile (KB) at 25 % / end | " << rss_first.file << " / " << rss_last.file << " | |\n"
     << "| **survivor RssAnon** (heap, KB) at 25 % / end | " << rss_first.anon << " / " << rss_last.anon
     << " | flat |\n"
     << "| **survivor RssAnon trend** (least squares over " << anon_samples.size()
     << " samples, 1/s from 25 %): whole / first half / second half | " << kb_min(anon_samples) << " / "
     << kb_min({anon_samples.begin(), anon_samples.begin() + half}) << " / "
     << kb_min({anon_samples.begin() + half, anon_samples.end()}) << " | ~0 |\n"
     << "| **leftover /dev/shm files** after the clean stop | " << left.size() << " | 0 |\n"
     << "| children that failed by themselves / reported errors | " << (ok ? 0 : 1) << " / " << t.errors
     << " | 0 / 0 |\n";
  for (const auto& e : t.error_lines) md << "\nerror: " << e << "\n";
  for (const auto& f : left) md << "\nleftover: /dev/shm/" << f << "\n";
  const bool written = print_report("lcmx_bench_soak", md.str(), s.markdown);
  for (const auto& f : left) ::unlink(("/dev/shm/" + f).c_str());  // leave the machine clean
  const bool pass = written && ok && t.uncounted == 0 && t.dups == 0 && t.torn == 0 && t.bad == 0 && left.empty() &&
                    t.errors == 0;
  return pass ? 0 : 1;
}

}  // namespace
}  // namespace lcmxbench

int main(int argc, char** argv) {
  using namespace lcmxbench;
  CLI::App app{"lcmx soak: the demo's traffic while random processes are killed and restarted"};
  Settings s;
  std::string role;
  std::string image_size = "6200000", small_size = "256";
  app.add_option("--duration", s.duration_s, "seconds to run")->check(CLI::Range(5, 86400));
  app.add_option("--kill-every-ms", s.kill_every_ms, "kill and restart a random process this often (0: never)")
      ->check(CLI::Range(0, 3'600'000));
  app.add_option("--signal", s.signal, "KILL, TERM or INT")->check(CLI::IsMember({"KILL", "TERM", "INT"}));
  app.add_option("--subs", s.subs, "subscriber processes (sub-0 is never killed)")->check(CLI::Range(1, 16));
  app.add_option("--image-size", image_size, "image message size (K, M suffixes)");
  app.add_option("--image-hz", s.image_hz, "images per second")->check(CLI::Range(1, 1000));
  app.add_option("--small-topics", s.small_topics, "small topics")->check(CLI::Range(1, 1000));
  app.add_option("--small-hz", s.small_hz, "messages per second per small topic")->check(CLI::Range(1, 10000));
  app.add_option("--small-size", small_size, "small message size");
  app.add_option("--seed", s.seed, "seed of the choice of process to kill");
  app.add_option("--url", s.url, "lcmx discovery URL (inside the private namespace)");
  app.add_option("--markdown", s.markdown, "also write the table to this file");
  add_hidden(app, "--role", role);  // the children
  try {
    app.parse(argc, argv);
    s.image_size = parse_size(image_size, sizeof(Header) + 8);
    s.small_size = parse_size(small_size, sizeof(Header) + 8);
  } catch (const CLI::ParseError& e) {
    return app.exit(e);
  } catch (const std::invalid_argument& e) {
    return bad_options("lcmx_bench_soak", e.what());
  }
  if (role.empty()) return orchestrate(s, self_exe());
  log_to_stderr(role);
  if (role == "image-pub") return run_pub(s, true);
  if (role == "small-pub") return run_pub(s, false);
  if (role.rfind("sub-", 0) == 0) return run_sub(s, std::atoi(role.c_str() + 4));
  std::fprintf(stderr, "lcmx_bench_soak: unknown role '%s'\n", role.c_str());
  return 2;
}
