// `liblcm`: stock liblcm udpm (lcm_publish / lcm_handle) between two processes. Both run in
// a network namespace of their own whose multicast route is loopback (see main.cpp), since
// liblcm 1.3.1 joins groups on INADDR_ANY. The message is the same lcm-gen bench_t the lcmx
// typed path carries: encoded by the publisher, decoded by the subscriber.
#include <lcm/lcm.h>
#include <poll.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <string>
#include <vector>

#include "latency/roles.hpp"
#include "lcmx_examples/bench_t.hpp"

namespace lcmxbench {
namespace {

std::string channel_of(const RoleConfig& cfg) { return "LCMXBENCH_" + cfg.name; }

struct Lcm {
  lcm_t* lcm = nullptr;
  explicit Lcm(const std::string& url) : lcm(lcm_create(url.c_str())) {}
  ~Lcm() {
    if (lcm) lcm_destroy(lcm);
  }
};

struct SubState {
  Recorder* rec;
  lcmx_examples::bench_t msg;  // decoded into again and again: its buffer is reused
  std::int64_t decode_errors = 0;
};

void on_message(const lcm_recv_buf_t* rbuf, const char*, void* user) {
  auto* st = static_cast<SubState*>(user);
  if (st->msg.decode(rbuf->data, 0, static_cast<int>(rbuf->data_size)) < 0) {
    ++st->decode_errors;
    return;
  }
  const std::int64_t lat = now_ns() - st->msg.send_ns;
  st->rec->record(static_cast<std::size_t>(st->msg.size), st->msg.seq, lat);
  send_ack(kAckFd, st->msg.seq);
}

}  // namespace

int run_liblcm_sub(const RoleConfig& cfg) {
  Lcm l(cfg.url);
  if (!l.lcm) {
    report_error("liblcm: lcm_create(" + cfg.url + ") failed");
    return 1;
  }
  Recorder rec(cfg.plan);
  SubState st{&rec, {}, 0};
  std::size_t cap = 0;
  for (const auto& p : cfg.plan) cap = std::max(cap, p.size);
  st.msg.data.reserve(cap);
  const std::string ch = channel_of(cfg);
  if (!lcm_subscribe(l.lcm, ch.c_str(), &on_message, &st)) {
    report_error("liblcm: lcm_subscribe failed");
    return 1;
  }
  const int lfd = lcm_get_fileno(l.lcm);  // liblcm opens its receive socket lazily: now
  if (lfd < 0) {
    report_error("liblcm: lcm_get_fileno failed");
    return 1;
  }
  report_line("ready");
  const std::int64_t give_up = now_ns() + 600'000'000'000;  // bounded: 10 min at most
  while (now_ns() < give_up) {
    pollfd p[2] = {{lfd, POLLIN, 0}, {kCtlFd, POLLIN, 0}};
    const int r = ::poll(p, 2, 100);
    if (r < 0 && errno == EINTR) continue;
    if (r < 0) break;
    if (p[0].revents & POLLIN) lcm_handle(l.lcm);
    else if (p[1].revents & (POLLIN | POLLHUP)) break;  // publisher done (or gone)
  }
  rec.report();
  if (st.decode_errors) report_line("note liblcm: " + std::to_string(st.decode_errors) + " messages did not decode");
  report_line("done");
  return 0;
}

int run_liblcm_pub(const RoleConfig& cfg) {
  Lcm l(cfg.url);
  if (!l.lcm) {
    report_error("liblcm: lcm_create(" + cfg.url + ") failed");
    return 1;
  }
  const std::string ch = channel_of(cfg);
  lcmx_examples::bench_t msg;
  std::vector<std::uint8_t> buf;
  std::int64_t publish_errors = 0;
  Driver d;
  d.prepare = [&](std::size_t size) {
    fill_bench(msg, size);
    buf.resize(static_cast<std::size_t>(msg.getEncodedSize()));
  };
  d.send = [&](std::int64_t seq, std::size_t) {
    msg.seq = seq;
    msg.send_ns = now_ns();
    msg.encode(buf.data(), 0, static_cast<int>(buf.size()));
    if (lcm_publish(l.lcm, ch.c_str(), buf.data(), static_cast<unsigned>(buf.size())) < 0) ++publish_errors;
  };
  d.wait_ack = [&](std::int64_t seq, int timeout_ms) { return wait_ack(kAckFd, seq, timeout_ms); };
  const bool ok = run_driver(cfg, d);
  if (publish_errors) report_line("note liblcm: lcm_publish failed " + std::to_string(publish_errors) + " times");
  send_end();
  report_line("done");
  return ok ? 0 : 1;
}

}  // namespace lcmxbench
