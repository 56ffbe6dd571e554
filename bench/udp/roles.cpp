// Child roles of lcmx_bench_udp that bench/latency does not have:
//  - lcmx-udp-sub / lcmx-udp-pub: Publisher<bench_t> on host 0 -> Subscriber<bench_t> on host 1,
//    both with a vehicle group (RuntimeOptions::vehicle_url, iface=eth), so the pair's path is
//    udp (checked and reported as a note);
//  - stream roles (lcmx-udp / liblcm, "-stream-pub" / "-stream-sub"): the publisher sends
//    plan[0].messages messages at --rate Hz without waiting for acks; the subscriber records
//    what arrives (loss = sent - received).
// The ping-pong liblcm roles are bench/latency's (run_liblcm_sub / run_liblcm_pub).
#include <lcm/lcm.h>
#include <poll.h>
#include <sys/resource.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <memory>
#include <string>
#include <thread>

#include "udp/roles.hpp"
#include "harness/endpoints.hpp"
#include "harness/options.hpp"
#include "lcmx/core.hpp"

namespace lcmxbench::udp {
namespace {

constexpr auto kMatchTimeout = std::chrono::milliseconds(15000);

std::string channel_of(const RoleConfig& cfg) { return "LCMXBENCH_" + cfg.name; }

lcmx::RuntimeOptions runtime_options(const UdpConfig& u) {
  lcmx::RuntimeOptions o;  // not from_env(): the bench never uses the default groups
  o.discovery_url = u.base.url;
  o.vehicle_url = u.vehicle_url;
  o.beacon_period = std::chrono::milliseconds(200);
  o.vehicle_key = u.key_file;  // keyed groups (--keys): authenticated, or encrypted with crypt
  o.vehicle_crypt = !u.key_file.empty() && u.crypt;
  return o;
}

// "note cpu <who> <µs>": this process's CPU time (user + system) so far (--keys: CPU per MB).
void report_cpu(const char* who) {
  rusage r{};
  ::getrusage(RUSAGE_SELF, &r);
  const long long us = (r.ru_utime.tv_sec + r.ru_stime.tv_sec) * 1000000LL + r.ru_utime.tv_usec + r.ru_stime.tv_usec;
  report_line(std::string("note cpu ") + who + " " + std::to_string(us));
}

// Streams: waits for 'E' on the ctl fd, then up to `grace_ms` more while messages still come.
template <class Pump, class Count>
void stream_tail(Pump pump, Count count, int expected, int grace_ms) {
  wait_end(kCtlFd, 600'000);
  const std::int64_t deadline = now_ns() + static_cast<std::int64_t>(grace_ms) * 1'000'000;
  while (count() < expected && now_ns() < deadline) pump(10);
}

}  // namespace

int run_lcmx_udp_sub(const UdpConfig& u, bool stream) {
  const RoleConfig& cfg = u.base;
  log_to_stderr(cfg.role);
  try {
    auto rt = lcmx::Runtime::create(runtime_options(u));
    lcmx::NodeOptions no;
    no.executor.wait = wait_strategy(cfg.wait);
    auto node = rt.create_node("bench_sub", no);
    Recorder rec(cfg.plan);
    std::atomic<int> received{0};
    lcmx::SubscriberOptions so;
    so.queue_depth = 64;
    auto sub = node.subscribe<lcmx_examples::bench_t>(
        channel_of(cfg),
        [&](const lcmx_examples::bench_t& m) {
          rec.record(static_cast<std::size_t>(m.size), m.seq, now_ns() - m.send_ns);
          received.fetch_add(1);
          if (!stream) send_ack(kAckFd, m.seq);
        },
        so);
    report_line("ready");
    if (!sub.wait_for_publishers(1, kMatchTimeout)) {
      report_error("subscriber: wait_for_publishers(1, 15 s) timed out");
      return 1;
    }
    const std::string paths = paths_of(sub.stats());
    report_line("note path at match: " + (paths.empty() ? std::string("(none)") : paths));
    send_ack(kAckFd, kMatchedRecord);
    if (stream) {
      stream_tail([](int ms) { std::this_thread::sleep_for(std::chrono::milliseconds(ms)); },
                  [&] { return received.load(); }, cfg.plan.front().messages, 1000);
    } else {
      wait_end(kCtlFd, 600'000);
    }
    const auto st = sub.stats();
    sub.reset();
    rec.report();
    report_delivery("subscriber", st);
    report_cpu("sub");
  } catch (const std::exception& e) {
    report_error(std::string("subscriber: ") + e.what());
    return 1;
  }
  report_line("done");
  return 0;
}

int run_lcmx_udp_pub(const UdpConfig& u, bool stream) {
  const RoleConfig& cfg = u.base;
  log_to_stderr(cfg.role);
  bool ok = false;
  try {
    auto rt = lcmx::Runtime::create(runtime_options(u));
    auto node = rt.create_node("bench_pub");
    lcmx::PublisherOptions po;
    po.max_message_size = std::max<std::size_t>(po.max_message_size, max_size(cfg.plan) + 4096);
    auto pub = node.advertise<lcmx_examples::bench_t>(channel_of(cfg), po);
    if (!pub.wait_for_subscribers(1, kMatchTimeout)) {
      report_error("publisher: wait_for_subscribers(1, 15 s) timed out");
    } else if (!wait_ack(kAckFd, kMatchedRecord, static_cast<int>(kMatchTimeout.count()))) {
      report_error("publisher: the subscriber did not match this publisher within 15 s");
    } else {
      lcmx_examples::bench_t msg;
      auto prepare = [&](std::size_t size) { fill_bench(msg, size); };
      auto send = [&](std::int64_t seq) {
        msg.seq = seq;
        msg.send_ns = now_ns();
        pub.publish(msg);
      };
      if (stream) {
        ok = run_stream(cfg, u.rate_hz, u.burst, prepare, send);
      } else {
        Driver d;
        d.prepare = prepare;
        d.send = [&](std::int64_t seq, std::size_t) { send(seq); };
        d.wait_ack = [&](std::int64_t seq, int timeout_ms) { return wait_ack(kAckFd, seq, timeout_ms); };
        ok = run_driver(cfg, d);
      }
    }
  } catch (const std::exception& e) {
    report_error(std::string("publisher: ") + e.what());
  }
  report_cpu("pub");
  send_end();
  report_line("done");
  return ok ? 0 : 1;
}

bool run_stream(const RoleConfig& cfg, double rate_hz, int burst, const std::function<void(std::size_t)>& prepare,
                const std::function<void(std::int64_t)>& send) {
  const SizePlan& p = cfg.plan.front();
  prepare(p.size);
  const auto period = std::chrono::duration_cast<std::chrono::steady_clock::duration>(
      std::chrono::duration<double>(1.0 / rate_hz));
  auto next = std::chrono::steady_clock::now();
  for (int i = 0; i < p.messages; ++i) {
    send(make_seq(i + 1, true));
    if ((i + 1) % std::max(burst, 1) != 0 && i + 1 < p.messages) continue;  // rest of the burst
    next += period;
    std::this_thread::sleep_until(next);  // pacing the rate
  }
  report_line("sent " + std::to_string(p.size) + ' ' + std::to_string(p.messages) + " 0");
  return true;
}

int run_hog() {
  const auto end = std::chrono::steady_clock::now() + std::chrono::minutes(10);
  volatile std::uint64_t x = 0;
  while (std::chrono::steady_clock::now() < end)
    for (int i = 0; i < 1000000; ++i) x = x + 1;
  return 0;
}

// ---- liblcm stream roles ----

namespace {
struct LcmSub {
  Recorder* rec;
  lcmx_examples::bench_t msg;
  int received = 0;
};
void on_lcm(const lcm_recv_buf_t* rbuf, const char*, void* user) {
  auto* st = static_cast<LcmSub*>(user);
  if (st->msg.decode(rbuf->data, 0, static_cast<int>(rbuf->data_size)) < 0) return;
  st->rec->record(static_cast<std::size_t>(st->msg.size), st->msg.seq, now_ns() - st->msg.send_ns);
  ++st->received;
}
}  // namespace

int run_liblcm_stream_sub(const UdpConfig& u) {
  const RoleConfig& cfg = u.base;
  lcm_t* lcm = lcm_create(cfg.url.c_str());
  if (!lcm) {
    report_error("liblcm: lcm_create(" + cfg.url + ") failed");
    return 1;
  }
  Recorder rec(cfg.plan);
  LcmSub st{&rec, {}, 0};
  lcm_subscribe(lcm, channel_of(cfg).c_str(), &on_lcm, &st);
  const int fd = lcm_get_fileno(lcm);
  report_line("ready");
  auto pump = [&](int ms) {
    pollfd p{fd, POLLIN, 0};
    if (::poll(&p, 1, ms) > 0) lcm_handle(lcm);
  };
  // Receive until the publisher says it is done, then drain.
  for (;;) {
    pollfd p[2] = {{fd, POLLIN, 0}, {kCtlFd, POLLIN, 0}};
    const int r = ::poll(p, 2, 100);
    if (r < 0 && errno == EINTR) continue;
    if (r < 0) break;
    if (p[0].revents & POLLIN) lcm_handle(lcm);
    else if (p[1].revents & (POLLIN | POLLHUP)) break;
  }
  const std::int64_t deadline = now_ns() + 1'000'000'000;
  while (st.received < cfg.plan.front().messages && now_ns() < deadline) pump(10);
  rec.report();
  lcm_destroy(lcm);
  report_line("done");
  return 0;
}

int run_liblcm_stream_pub(const UdpConfig& u) {
  const RoleConfig& cfg = u.base;
  lcm_t* lcm = lcm_create(cfg.url.c_str());
  if (!lcm) {
    report_error("liblcm: lcm_create(" + cfg.url + ") failed");
    return 1;
  }
  lcmx_examples::bench_t msg;
  std::vector<std::uint8_t> buf;
  const std::string ch = channel_of(cfg);
  const bool ok = run_stream(
      cfg, u.rate_hz, u.burst,
      [&](std::size_t size) { fill_bench(msg, size); },
      [&](std::int64_t seq) {
        msg.seq = seq;
        msg.send_ns = now_ns();
        buf.resize(static_cast<std::size_t>(msg.getEncodedSize()));
        msg.encode(buf.data(), 0, static_cast<int>(buf.size()));
        lcm_publish(lcm, ch.c_str(), buf.data(), static_cast<unsigned>(buf.size()));
      });
  send_end();
  lcm_destroy(lcm);
  report_line("done");
  return ok ? 0 : 1;
}

}  // namespace lcmxbench::udp
