// Child roles of lcmx_bench_bridge:
//  - zmq-pub / zmq-sub: the per-subscriber stand-in for DDS unicast / CyberRT. The publisher
//    holds one ZeroMQ PUSH socket (one TCP connection) per subscriber and sends every message
//    to each, zero-copy from its own buffer (zmq_msg_init_data); each subscriber binds a PULL
//    socket on host B and takes the receive time when zmq_msg_recv returns the whole message.
//  - lcmx-pub / lcmx-sub: lcmx's public API only. RawPublisher::loan(size), write the 24-byte
//    header, publish(loan, size); RawSubscriber reads the header zero-copy in its callback.
//    Between hosts the message goes through `lcmx bridge` (started by the orchestrator).
// See roles.hpp for the line protocol.
#include "bridge/roles.hpp"

#include <fcntl.h>
#include <linux/futex.h>
#include <poll.h>
#include <sys/mman.h>
#include <sys/syscall.h>
#include <unistd.h>
#include <zmq.h>

#include <atomic>
#include <climits>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <functional>
#include <memory>
#include <optional>
#include <sstream>
#include <thread>
#include <vector>
#include <zmq.hpp>

#include "harness/endpoints.hpp"
#include "harness/options.hpp"
#include "harness/pingpong.hpp"
#include "lcmx/core.hpp"

namespace lcmxbench::bridge {
namespace {

// Receive records of one subscriber: the receiving thread appends (no system call, no
// allocation), a reporter thread writes them as "r" lines every 5 ms. So the callback of one
// subscriber does not delay another subscriber that waits for the same CPU, and report lines
// never wake the orchestrator while a message is being delivered (experiment 3).
class RxLog {
 public:
  RxLog() : recs_(kCapacity), reporter_([this] { run(); }) {}
  RxLog(const RxLog&) = delete;
  RxLog& operator=(const RxLog&) = delete;
  ~RxLog() { stop(); }

  // One producer thread only. Records beyond kCapacity are dropped (counted).
  void add(const Header& h, std::size_t got, std::int64_t recv_ns) noexcept {
    const std::size_t i = n_.load(std::memory_order_relaxed);
    if (i >= kCapacity) {
      overflow_.fetch_add(1, std::memory_order_relaxed);
      return;
    }
    recs_[i] = Rec{h.seq, h.send_ns, recv_ns, got};
    n_.store(i + 1, std::memory_order_release);  // pairs with the acquire in flush()
  }
  // Stops the reporter and writes what is left. Idempotent.
  void stop() {
    if (stop_.exchange(true)) return;
    reporter_.join();
    flush();
    if (overflow_) report_line("note subscriber: " + std::to_string(overflow_.load()) + " receive records lost (log full)");
  }

 private:
  static constexpr std::size_t kCapacity = 1 << 16;
  struct Rec {
    std::int64_t seq, send_ns, recv_ns;
    std::size_t got;
  };
  void flush() {
    const std::size_t n = n_.load(std::memory_order_acquire);
    std::string out;
    for (; done_ < n; ++done_) {
      const Rec& r = recs_[done_];
      char line[128];
      std::snprintf(line, sizeof line, "r %lld %zu %lld %lld\n", static_cast<long long>(r.seq), r.got,
                    static_cast<long long>(r.send_ns), static_cast<long long>(r.recv_ns));
      out += line;
    }
    if (!out.empty()) {
      out.pop_back();  // report_line adds the last '\n'
      report_line(out);
    }
  }
  void run() {
    while (!stop_.load()) {
      std::this_thread::sleep_for(std::chrono::milliseconds(5));  // a tick, not a synchronisation
      flush();
    }
  }

  std::vector<Rec> recs_;
  std::atomic<std::size_t> n_{0};
  std::atomic<std::uint64_t> overflow_{0};
  std::size_t done_ = 0;  // reporter thread only (then stop())
  std::atomic<bool> stop_{false};
  std::thread reporter_;
};

// The command loop of both publishers. send(seq, size) hands one message to the transport.
int publisher_loop(const std::function<void(std::int64_t, std::size_t)>& send) {
  CommandReader ctl;
  for (;;) {
    const auto line = ctl.next(-1);
    if (!line) continue;
    std::istringstream in(*line);
    std::string cmd;
    in >> cmd;
    if (cmd == "quit") break;
    if (cmd == "send") {
      std::int64_t seq = 0;
      std::size_t size = 0;
      in >> seq >> size;
      send(seq, size);
      report_line("s " + std::to_string(seq));
    } else if (cmd == "stream") {
      // Paced at `hz` with sleep_until (pacing, not synchronisation); seqs k, k+1, ... measured.
      std::size_t size = 0;
      int count = 0;
      double hz = 0;
      std::int64_t k = 0;
      in >> size >> count >> hz >> k;
      const auto period = std::chrono::duration_cast<std::chrono::steady_clock::duration>(
          std::chrono::duration<double>(1.0 / hz));
      auto next = std::chrono::steady_clock::now();
      const std::int64_t t0 = now_ns();
      for (int i = 0; i < count; ++i) {
        send(make_seq(k + i, true), size);
        next += period;
        std::this_thread::sleep_until(next);
      }
      report_line("streamed " + std::to_string(count) + ' ' + std::to_string(t0) + ' ' +
                  std::to_string(now_ns()));
    } else {
      report_error("unknown command '" + *line + "'");
    }
  }
  return 0;
}

// ---- ZeroMQ ----

// A message buffer handed to ZeroMQ zero-copy; reused only once every socket released it.
struct ZBuf {
  std::vector<std::byte> data;
  std::atomic<int> refs{0};
};
void zbuf_free(void*, void* hint) {
  static_cast<ZBuf*>(hint)->refs.fetch_sub(1, std::memory_order_acq_rel);
}

}  // namespace

int run_zmq_pub(const ChildConfig& c) {
  try {
    zmq::context_t ctx(1);
    std::vector<zmq::socket_t> socks;
    for (const auto& ep : c.endpoints) {
      zmq::socket_t s(ctx, zmq::socket_type::push);
      s.set(zmq::sockopt::linger, 0);
      s.connect(ep);
      socks.push_back(std::move(s));
    }
    // 8 buffers with the pattern written once (pages touched before any timing).
    std::vector<std::unique_ptr<ZBuf>> pool;
    for (int i = 0; i < 8; ++i) {
      auto b = std::make_unique<ZBuf>();
      b->data.resize(std::max<std::size_t>(c.max_size, sizeof(Header)));
      for (std::size_t j = 0; j < b->data.size(); ++j) b->data[j] = static_cast<std::byte>(j * 31u);
      pool.push_back(std::move(b));
    }
    report_line("ready");
    bool failed = false;
    auto send = [&](std::int64_t seq, std::size_t size) {
      ZBuf* buf = nullptr;
      const std::int64_t deadline = now_ns() + 10'000'000'000;
      while (!buf) {
        for (auto& b : pool)
          if (b->refs.load(std::memory_order_acquire) == 0) {
            buf = b.get();
            break;
          }
        if (!buf) {
          if (now_ns() > deadline) {
            if (!failed) report_error("zmq-pub: no free buffer for 10 s (ZeroMQ holds all 8)");
            failed = true;
            return;
          }
          std::this_thread::sleep_for(std::chrono::microseconds(100));
        }
      }
      buf->refs.store(static_cast<int>(socks.size()), std::memory_order_relaxed);
      const Header h{seq, now_ns(), static_cast<std::int64_t>(size)};
      std::memcpy(buf->data.data(), &h, sizeof h);
      for (auto& s : socks) {
        zmq_msg_t m;
        zmq_msg_init_data(&m, buf->data.data(), size, &zbuf_free, buf);
        while (zmq_msg_send(&m, s.handle(), 0) < 0) {
          if (zmq_errno() == EINTR) continue;
          report_error(std::string("zmq-pub: zmq_msg_send: ") + zmq_strerror(zmq_errno()));
          zmq_msg_close(&m);
          break;
        }
      }
    };
    publisher_loop(send);
  } catch (const std::exception& e) {
    report_error(std::string("zmq-pub: ") + e.what());
    return 1;
  }
  report_line("done");
  return 0;
}

int run_zmq_sub(const ChildConfig& c) {
  try {
    zmq::context_t ctx(1);
    zmq::socket_t s(ctx, zmq::socket_type::pull);
    s.set(zmq::sockopt::linger, 0);
    s.bind(c.endpoints.at(0));
    report_line("ready");
    CommandReader ctl;
    RxLog log;
    std::uint64_t received = 0, short_msgs = 0;
    for (;;) {
      zmq::pollitem_t items[] = {{s.handle(), 0, ZMQ_POLLIN, 0}, {nullptr, kCmdFd, ZMQ_POLLIN, 0}};
      zmq::poll(items, 2, std::chrono::milliseconds(-1));
      if (items[0].revents & ZMQ_POLLIN) {
        zmq::message_t m;
        while (s.recv(m, zmq::recv_flags::dontwait)) {
          const std::int64_t t = now_ns();
          if (m.size() < sizeof(Header)) {
            ++short_msgs;
            continue;
          }
          Header h;
          std::memcpy(&h, m.data(), sizeof h);
          log.add(h, m.size(), t);
          ++received;
        }
      }
      if (items[1].revents) {
        const auto line = ctl.next(0);
        if (line && *line == "quit") break;
      }
    }
    log.stop();
    report_line("note zmq-sub: received=" + std::to_string(received) +
                (short_msgs ? " short=" + std::to_string(short_msgs) : std::string()));
  } catch (const std::exception& e) {
    report_error(std::string("zmq-sub: ") + e.what());
    return 1;
  }
  report_line("done");
  return 0;
}

// ---- floor: one process wakes N processes through a futex in shared memory ----

namespace {

// The shared page of the floor roles: the futex word, then the header of the "message".
struct FloorPage {
  std::atomic<std::uint32_t> word;
  std::uint32_t reserved;
  Header h;
};

FloorPage* map_floor(const std::string& name) {
  const std::string shm = "/" + name;
  const int fd = ::shm_open(shm.c_str(), O_RDWR | O_CREAT, 0600);
  if (fd < 0) throw std::runtime_error("shm_open " + shm + ": " + std::strerror(errno));
  if (::ftruncate(fd, 4096) != 0) {
    ::close(fd);
    throw std::runtime_error("ftruncate " + shm + ": " + std::strerror(errno));
  }
  void* p = ::mmap(nullptr, 4096, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
  ::close(fd);
  if (p == MAP_FAILED) throw std::runtime_error("mmap " + shm + ": " + std::strerror(errno));
  return static_cast<FloorPage*>(p);
}

long futex(std::atomic<std::uint32_t>* w, int op, std::uint32_t val, const timespec* ts) {
  return ::syscall(SYS_futex, reinterpret_cast<std::uint32_t*>(w), op, val, ts, nullptr, 0);
}

}  // namespace

int run_floor_pub(const ChildConfig& c) {
  try {
    FloorPage* page = map_floor(c.channel);
    report_line("ready");
    publisher_loop([&](std::int64_t seq, std::size_t size) {
      page->h = Header{seq, now_ns(), static_cast<std::int64_t>(size)};
      page->word.fetch_add(1, std::memory_order_release);  // pairs with the subscribers' acquire
      futex(&page->word, FUTEX_WAKE, INT_MAX, nullptr);
    });
    ::munmap(page, 4096);
    ::shm_unlink(("/" + c.channel).c_str());
  } catch (const std::exception& e) {
    report_error(std::string("floor-pub: ") + e.what());
    return 1;
  }
  report_line("done");
  return 0;
}

int run_floor_sub(const ChildConfig& c) {
  try {
    FloorPage* page = map_floor(c.channel);
    RxLog log;
    CommandReader ctl;
    report_line("ready");
    std::uint32_t seen = page->word.load(std::memory_order_acquire);
    for (;;) {
      const timespec ts{0, 100'000'000};
      futex(&page->word, FUTEX_WAIT, seen, &ts);
      const std::uint32_t now = page->word.load(std::memory_order_acquire);
      if (now != seen) {
        const std::int64_t t = now_ns();
        seen = now;
        const Header h = page->h;
        log.add(h, static_cast<std::size_t>(h.size), t);
      }
      if (const auto line = ctl.next(0); line && *line == "quit") break;
    }
    log.stop();
    ::munmap(page, 4096);
    ::shm_unlink(("/" + c.channel).c_str());
  } catch (const std::exception& e) {
    report_error(std::string("floor-sub: ") + e.what());
    return 1;
  }
  report_line("done");
  return 0;
}

// ---- lcmx ----

namespace {

lcmx::RuntimeOptions lcmx_options(const ChildConfig& c) {
  lcmx::RuntimeOptions o;  // not from_env(): never the default groups
  o.discovery_url = c.discovery_url;
  o.beacon_period = std::chrono::milliseconds(200);
  o.topic_class[c.channel] = lcmx::TopicClass::large;  // bridged from the first message on
  return o;
}

}  // namespace

int run_lcmx_pub(const ChildConfig& c) {
  log_to_stderr(c.role);
  try {
    auto rt = lcmx::Runtime::create(lcmx_options(c));
    auto node = rt.create_node("bench_bridge_pub");
    lcmx::PublisherOptions po;
    po.max_message_size = std::max<std::size_t>(po.max_message_size, c.max_size + 4096);
    auto pub = node.advertise_raw(c.channel, po);
    report_line("ready");
    publisher_loop([&](std::int64_t seq, std::size_t size) {
      const Header h{seq, now_ns(), static_cast<std::int64_t>(size)};
      auto loan = pub.loan(size);
      std::memcpy(loan.data(), &h, sizeof h);  // header only: the payload is not rewritten
      pub.publish(std::move(loan), size);
    });
  } catch (const std::exception& e) {
    report_error(std::string("lcmx-pub: ") + e.what());
    return 1;
  }
  report_line("done");
  return 0;
}

int run_lcmx_sub(const ChildConfig& c) {
  log_to_stderr(c.role);
  try {
    auto rt = lcmx::Runtime::create(lcmx_options(c));
    lcmx::NodeOptions no;
    no.executor.wait = wait_strategy(c.wait);
    auto node = rt.create_node("bench_bridge_sub", no);
    std::atomic<std::uint64_t> short_msgs{0};
    RxLog log;
    auto sub = node.subscribe_raw(c.channel, [&](const lcmx::RawMessage& m) {
      const std::int64_t t = now_ns();
      if (m.data.size() < sizeof(Header)) {
        short_msgs.fetch_add(1);
        return;
      }
      Header h;
      std::memcpy(&h, m.data.data(), sizeof h);  // zero-copy read of the header
      log.add(h, m.data.size(), t);
    });
    report_line("ready");
    CommandReader ctl;
    for (;;) {
      const auto line = ctl.next(-1);
      if (line && *line == "quit") break;
    }
    const auto st = sub.stats();
    sub.reset();  // waits for a running callback
    log.stop();
    const std::string paths = paths_of(st);
    report_line("note lcmx-sub: delivered=" + std::to_string(st.delivered) + " drops=" + std::to_string(st.drops) +
                " paths=" + (paths.empty() ? std::string("(none)") : paths) +
                (short_msgs ? " short=" + std::to_string(short_msgs.load()) : std::string()));
  } catch (const std::exception& e) {
    report_error(std::string("lcmx-sub: ") + e.what());
    return 1;
  }
  report_line("done");
  return 0;
}

}  // namespace lcmxbench::bridge
