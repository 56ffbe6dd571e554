// lcmx paths through the public API only (lcmx/core.hpp):
//  - lcmx-shm:   Publisher<bench_t>::publish(const bench_t&) -> Subscriber<bench_t> with a
//                `const bench_t&` callback in another process (encode into a slot, decode out);
//  - lcmx-loan:  RawPublisher::loan(size), write a 16-byte header {seq, send_ns} only, then
//                publish(std::move(loan), size) -> RawSubscriber reads the header zero-copy;
//  - lcmx-intra: publisher and subscriber nodes in one process; the callback takes
//                std::shared_ptr<const bench_t> (the publisher's own object, no copy).
// Acks go back through a pipe side channel (8-byte seq), not through lcmx; they are not part
// of the measured one-way time.
#include <fcntl.h>
#include <poll.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <exception>
#include <memory>
#include <string>
#include <vector>

#include "latency/roles.hpp"
#include "harness/endpoints.hpp"
#include "harness/options.hpp"
#include "lcmx/core.hpp"

namespace lcmxbench {
namespace {

constexpr auto kMatchTimeout = std::chrono::milliseconds(15000);

struct LoanHeader {
  std::int64_t seq;
  std::int64_t send_ns;
};
static_assert(sizeof(LoanHeader) == 16);

std::string channel_of(const RoleConfig& cfg, const char* what) {
  return "LCMXBENCH_" + cfg.name + "_" + what;
}

lcmx::RuntimeOptions runtime_options(const RoleConfig& cfg) {
  lcmx::RuntimeOptions o;  // not from_env(): the bench never uses the default group
  o.discovery_url = cfg.url;
  return o;
}

lcmx::NodeOptions sub_node_options(const RoleConfig& cfg) {
  lcmx::NodeOptions o;
  o.executor.wait = wait_strategy(cfg.wait);
  return o;
}

// Runs on the subscriber's executor thread, first call: pin that thread too.
struct ThreadPin {
  int cpu;
  bool done = false;
  void operator()() {
    if (!done) {
      pin_thread(cpu);
      done = true;
    }
  }
};

}  // namespace

int run_lcmx_sub(const RoleConfig& cfg, bool loan) {
  log_to_stderr(cfg.role, "");
  try {
    auto rt = lcmx::Runtime::create(runtime_options(cfg));
    auto node = rt.create_node("bench_sub", sub_node_options(cfg));
    Recorder rec(cfg.plan);
    ThreadPin pin{cfg.sub_cpu};
    lcmx::RawSubscriber raw;
    lcmx::Subscriber<lcmx_examples::bench_t> typed;
    if (loan) {
      raw = node.subscribe_raw(channel_of(cfg, "LOAN"), [&](const lcmx::RawMessage& m) {
        pin();
        if (m.data.size() < sizeof(LoanHeader)) return;
        LoanHeader h;
        std::memcpy(&h, m.data.data(), sizeof h);  // the 16-byte header only: zero-copy read
        rec.record(m.data.size(), h.seq, now_ns() - h.send_ns);
        send_ack(kAckFd, h.seq);
      });
    } else {
      typed = node.subscribe<lcmx_examples::bench_t>(
          channel_of(cfg, "SHM"), [&](const lcmx_examples::bench_t& m) {
            pin();
            rec.record(static_cast<std::size_t>(m.size), m.seq, now_ns() - m.send_ns);
            send_ack(kAckFd, m.seq);
          });
    }
    report_line("ready");
    const bool matched = loan ? raw.wait_for_publishers(1, kMatchTimeout)
                              : typed.wait_for_publishers(1, kMatchTimeout);
    if (!matched) {
      report_error("subscriber: wait_for_publishers(1, 15 s) timed out");
      return 1;
    }
    {
      // The path of the pair, read now: at the end the publisher may already have left.
      const std::string paths = paths_of(loan ? raw.stats() : typed.stats());
      report_line(std::string("note ") + (loan ? "lcmx-loan" : "lcmx-shm") + ": path at match: " +
                  (paths.empty() ? "(none listed in SubscriberStats::publishers)" : paths));
    }
    send_ack(kAckFd, kMatchedRecord);
    wait_end(kCtlFd, 600'000);
    const auto stats = loan ? raw.stats() : typed.stats();
    raw.reset();  // waits for a running callback: rec is ours alone after this
    typed.reset();
    rec.report();
    report_delivery(loan ? "lcmx-loan subscriber" : "lcmx-shm subscriber", stats);
  } catch (const std::exception& e) {
    report_error(std::string("subscriber: ") + e.what());
    return 1;
  }
  report_line("done");
  return 0;
}

int run_lcmx_pub(const RoleConfig& cfg, bool loan) {
  log_to_stderr(cfg.role, "");
  bool ok = false;
  try {
    auto rt = lcmx::Runtime::create(runtime_options(cfg));
    auto node = rt.create_node("bench_pub");
    lcmx::PublisherOptions po;
    po.max_message_size = std::max<std::size_t>(po.max_message_size, max_size(cfg.plan) + 4096);
    lcmx::RawPublisher raw;
    lcmx::Publisher<lcmx_examples::bench_t> typed;
    if (loan) raw = node.advertise_raw(channel_of(cfg, "LOAN"), po);
    else typed = node.advertise<lcmx_examples::bench_t>(channel_of(cfg, "SHM"), po);
    const bool matched = loan ? raw.wait_for_subscribers(1, kMatchTimeout)
                              : typed.wait_for_subscribers(1, kMatchTimeout);
    if (!matched) {
      report_error("publisher: wait_for_subscribers(1, 15 s) timed out");
      return 1;
    }
    if (!wait_ack(kAckFd, kMatchedRecord, static_cast<int>(kMatchTimeout.count()))) {
      report_error("publisher: the subscriber did not match this publisher within 15 s");
      return 1;
    }
    lcmx_examples::bench_t msg;
    Driver d;
    d.prepare = [&](std::size_t size) {
      if (loan) return;  // loan: the payload is left as is, only the header is written
      fill_bench(msg, size);
    };
    d.send = [&](std::int64_t seq, std::size_t size) {
      if (loan) {
        const std::int64_t t = now_ns();
        auto l = raw.loan(size);
        const LoanHeader h{seq, t};
        std::memcpy(l.data(), &h, sizeof h);
        raw.publish(std::move(l), size);
      } else {
        msg.seq = seq;
        msg.send_ns = now_ns();
        typed.publish(msg);
      }
    };
    d.wait_ack = [&](std::int64_t seq, int timeout_ms) { return wait_ack(kAckFd, seq, timeout_ms); };
    ok = run_driver(cfg, d);
  } catch (const std::exception& e) {
    report_error(std::string("publisher: ") + e.what());
  }
  send_end();
  report_line("done");
  return ok ? 0 : 1;
}

int run_lcmx_intra(const RoleConfig& cfg) {
  log_to_stderr(cfg.role, "");
  int acks[2];
  if (::pipe2(acks, O_CLOEXEC) != 0) {
    report_error(std::string("intra: pipe: ") + std::strerror(errno));
    return 1;
  }
  struct CloseFds {
    int* f;
    ~CloseFds() { ::close(f[0]); ::close(f[1]); }
  } close_fds{acks};
  bool ok = false;
  try {
    auto rt = lcmx::Runtime::create(runtime_options(cfg));
    // The subscriber's node first: with --pin split the process starts on the subscriber's
    // CPU, so its executor thread is born there; this thread moves to the publisher's CPU.
    auto sub_node = rt.create_node("bench_sub", sub_node_options(cfg));
    Recorder rec(cfg.plan);
    ThreadPin pin{cfg.sub_cpu};
    auto sub = sub_node.subscribe<lcmx_examples::bench_t>(
        channel_of(cfg, "INTRA"), [&](const std::shared_ptr<const lcmx_examples::bench_t>& m) {
          pin();
          rec.record(static_cast<std::size_t>(m->size), m->seq, now_ns() - m->send_ns);
          send_ack(acks[1], m->seq);
        });
    auto pub_node = rt.create_node("bench_pub");
    lcmx::PublisherOptions po;
    po.max_message_size = std::max<std::size_t>(po.max_message_size, max_size(cfg.plan) + 4096);
    auto pub = pub_node.advertise<lcmx_examples::bench_t>(channel_of(cfg, "INTRA"), po);
    pin_thread(cfg.pub_cpu);
    report_line("ready");
    if (!pub.wait_for_subscribers(1, kMatchTimeout)) {
      report_error("intra: wait_for_subscribers(1, 15 s) timed out");
      return 1;
    }
    std::shared_ptr<lcmx_examples::bench_t> cur = std::make_shared<lcmx_examples::bench_t>();
    std::int64_t copies = 0;
    Driver d;
    d.prepare = [&](std::size_t size) {
      cur = std::make_shared<lcmx_examples::bench_t>();
      fill_bench(*cur, size);
    };
    d.send = [&](std::int64_t seq, std::size_t) {
      // A published object is immutable: reuse it only if lcmx no longer holds it (not timed).
      if (cur.use_count() > 1) {
        cur = std::make_shared<lcmx_examples::bench_t>(*cur);
        ++copies;
      }
      cur->seq = seq;
      cur->send_ns = now_ns();
      pub.publish(std::shared_ptr<const lcmx_examples::bench_t>(cur));
    };
    d.wait_ack = [&](std::int64_t seq, int timeout_ms) { return wait_ack(acks[0], seq, timeout_ms); };
    ok = run_driver(cfg, d);
    const auto stats = sub.stats();
    sub.reset();
    rec.report();
    report_delivery("lcmx-intra subscriber", stats);
    if (copies) report_line("note lcmx-intra: lcmx still held the previous message " + std::to_string(copies) + " times (copied before the timestamp)");
  } catch (const std::exception& e) {
    report_error(std::string("intra: ") + e.what());
  }
  report_line("done");
  return ok ? 0 : 1;
}

}  // namespace lcmxbench
