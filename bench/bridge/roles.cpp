// Child roles of lcmx_bench_bridge:
//  - zmq-pub / zmq-sub: the per-subscriber stand-in for DDS unicast / CyberRT. The publisher
//    holds one ZeroMQ PUSH socket (one TCP connection) per subscriber and sends every message
//    to each, zero-copy from its own buffer (zmq_msg_init_data); each subscriber binds a PULL
//    socket on host B and takes the receive time when zmq_msg_recv returns the whole message.
//  - lcmx-pub / lcmx-sub: lcmx's public API only. RawPublisher::loan(size), write the 24-byte
//    header, publish(loan, size); RawSubscriber reads the header zero-copy in its callback.
//    Between hosts the message goes through `lcmx bridge` (started by the orchestrator).
// See roles.hpp for the line protocol.
#include "roles.hpp"

#include <poll.h>
#include <unistd.h>
#include <zmq.h>

#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include <atomic>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <functional>
#include <memory>
#include <optional>
#include <sstream>
#include <thread>
#include <zmq.hpp>

#include "common.hpp"
#include "lcmx/core.hpp"

namespace lcmxbench::bridge {
namespace {

// Reads command lines from kCtlIn. next() blocks up to timeout_ms; nullopt on timeout; "quit"
// at EOF (the orchestrator is gone).
class CtlReader {
 public:
  std::optional<std::string> next(int timeout_ms) {
    for (;;) {
      if (const auto pos = buf_.find('\n'); pos != std::string::npos) {
        std::string line = buf_.substr(0, pos);
        buf_.erase(0, pos + 1);
        return line;
      }
      if (eof_) return std::string("quit");
      pollfd p{kCtlIn, POLLIN, 0};
      const int r = ::poll(&p, 1, timeout_ms);
      if (r < 0 && errno == EINTR) continue;
      if (r == 0) return std::nullopt;
      char tmp[4096];
      const ssize_t n = ::read(kCtlIn, tmp, sizeof tmp);
      if (n < 0 && errno == EINTR) continue;
      if (n <= 0) eof_ = true;
      else buf_.append(tmp, static_cast<std::size_t>(n));
    }
  }

 private:
  std::string buf_;
  bool eof_ = false;
};

void report_rx(const Header& h, std::size_t got, std::int64_t recv_ns) {
  char line[128];
  std::snprintf(line, sizeof line, "r %lld %zu %lld %lld", static_cast<long long>(h.seq), got,
                static_cast<long long>(h.send_ns), static_cast<long long>(recv_ns));
  report_line(line);
}

// The command loop of both publishers. send(seq, size) hands one message to the transport.
int publisher_loop(const std::function<void(std::int64_t, std::size_t)>& send) {
  CtlReader ctl;
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
    CtlReader ctl;
    std::uint64_t received = 0, short_msgs = 0;
    for (;;) {
      zmq::pollitem_t items[] = {{s.handle(), 0, ZMQ_POLLIN, 0}, {nullptr, kCtlIn, ZMQ_POLLIN, 0}};
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
          report_rx(h, m.size(), t);
          ++received;
        }
      }
      if (items[1].revents) {
        const auto line = ctl.next(0);
        if (line && *line == "quit") break;
      }
    }
    report_line("note zmq-sub: received=" + std::to_string(received) +
                (short_msgs ? " short=" + std::to_string(short_msgs) : std::string()));
  } catch (const std::exception& e) {
    report_error(std::string("zmq-sub: ") + e.what());
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

void log_to_stderr(const std::string& role) {
  auto logger = spdlog::stderr_color_mt(role);
  spdlog::set_default_logger(logger);
  spdlog::set_level(spdlog::level::warn);
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
    if (c.wait == "spin") no.executor.wait = lcmx::WaitStrategy::spin_then_block;
    else if (c.wait == "busy") no.executor.wait = lcmx::WaitStrategy::busy_poll;
    auto node = rt.create_node("bench_bridge_sub", no);
    std::atomic<std::uint64_t> short_msgs{0};
    auto sub = node.subscribe_raw(c.channel, [&](const lcmx::RawMessage& m) {
      const std::int64_t t = now_ns();
      if (m.data.size() < sizeof(Header)) {
        short_msgs.fetch_add(1);
        return;
      }
      Header h;
      std::memcpy(&h, m.data.data(), sizeof h);  // zero-copy read of the header
      report_rx(h, m.data.size(), t);
    });
    report_line("ready");
    CtlReader ctl;
    for (;;) {
      const auto line = ctl.next(-1);
      if (line && *line == "quit") break;
    }
    const auto st = sub.stats();
    sub.reset();  // waits for a running callback
    std::string paths;
    for (const auto& p : st.publishers) paths += std::string(paths.empty() ? "" : ",") + lcmx::to_string(p.path);
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
