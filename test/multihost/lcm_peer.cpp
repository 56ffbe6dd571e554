// lcmx_mh_lcm_peer: stock liblcm on the other end of the multi-host interop tests. It speaks
// lcmx_examples::bench_t with lcmx_test_peer's content pattern, so both sides check content
// and order (lcmx_udpm_peer's raw payloads would not decode as an lcm-gen type).
//
//   lcmx_mh_lcm_peer pub URL CHANNEL COUNT RATE_HZ SIZE ID
//     prints "ready", publishes COUNT bench_t (seq 0..COUNT-1, data[0..7] = ID NUL-padded,
//     data[i >= 8] = (i * 131 + seq * 7) & 0xff) at RATE_HZ (0: as fast as possible), "done <n>".
//   lcmx_mh_lcm_peer sub URL CHANNEL COUNT TIMEOUT_MS
//     subscribes (joined before "ready" is printed), stops after COUNT messages or TIMEOUT_MS,
//     then prints
//     "SUMMARY received=R first=F last=L duplicates=D out_of_order=O gaps=G bad_content=B
//      decode_errors=E" and "END". Exit 0 iff R == COUNT.
// stdin EOF (the test process died) or "quit" ends either role early.
#include <lcm/lcm.h>
#include <poll.h>
#include <unistd.h>

#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <set>
#include <string>
#include <thread>

#include "lcmx_examples/bench_t.hpp"

namespace {

using Clock = std::chrono::steady_clock;

std::uint8_t pattern(std::size_t i, std::int64_t seq) {
  return static_cast<std::uint8_t>((i * 131u + static_cast<std::uint64_t>(seq) * 7u) & 0xffu);
}

std::int64_t now_ns() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return std::int64_t{ts.tv_sec} * 1'000'000'000 + ts.tv_nsec;
}

// True once stdin reached EOF or carried "quit" (any line starting with 'q').
bool stdin_closed() {
  pollfd p{STDIN_FILENO, POLLIN, 0};
  if (::poll(&p, 1, 0) <= 0) return false;
  char c[64];
  const ssize_t n = ::read(STDIN_FILENO, c, sizeof c);
  return n <= 0 || c[0] == 'q';
}

struct SubState {
  long received = 0, duplicates = 0, out_of_order = 0, gaps = 0, bad = 0, decode_errors = 0;
  std::int64_t first = -1, last = -1;
  std::set<std::int64_t> seen;
};

void on_message(const lcm_recv_buf_t* rbuf, const char*, void* user) {
  auto* st = static_cast<SubState*>(user);
  lcmx_examples::bench_t m;
  if (m.decode(rbuf->data, 0, static_cast<int>(rbuf->data_size)) < 0) {
    ++st->decode_errors;
    return;
  }
  ++st->received;
  bool ok = m.size == static_cast<std::int32_t>(m.data.size());
  for (std::size_t i = 8; ok && i < m.data.size(); ++i) ok = m.data[i] == pattern(i, m.seq);
  if (!ok) ++st->bad;
  if (st->first < 0) st->first = m.seq;
  if (!st->seen.insert(m.seq).second) ++st->duplicates;
  else if (st->last >= 0 && m.seq < st->last) ++st->out_of_order;
  else if (st->last >= 0 && m.seq > st->last + 1) st->gaps += m.seq - st->last - 1;
  if (m.seq > st->last) st->last = m.seq;
}

int usage() {
  std::fprintf(stderr,
               "usage: lcmx_mh_lcm_peer pub URL CHANNEL COUNT RATE_HZ SIZE ID\n"
               "       lcmx_mh_lcm_peer sub URL CHANNEL COUNT TIMEOUT_MS\n");
  return 2;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2) return usage();
  const std::string cmd = argv[1];
  if (cmd == "pub" && argc == 8) {
    lcm_t* lcm = lcm_create(argv[2]);
    if (lcm == nullptr) {
      std::printf("FATAL lcm_create(%s) failed\n", argv[2]);
      return 1;
    }
    const long count = std::atol(argv[4]);
    const double rate = std::atof(argv[5]);
    const std::string id = argv[7];
    lcmx_examples::bench_t m;
    m.size = static_cast<std::int32_t>(std::max<long>(std::atol(argv[6]), 8));
    m.data.resize(static_cast<std::size_t>(m.size));
    std::vector<std::uint8_t> buf;
    std::printf("ready\n");
    std::fflush(stdout);
    auto next = Clock::now();
    const auto period = rate > 0 ? std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(1.0 / rate))
                                 : Clock::duration::zero();
    long sent = 0;
    for (long seq = 0; seq < count; ++seq) {
      if (stdin_closed()) break;
      m.seq = seq;
      m.send_ns = now_ns();
      for (std::size_t i = 0; i < m.data.size(); ++i)
        m.data[i] = i < 8 ? (i < id.size() ? static_cast<std::uint8_t>(id[i]) : 0) : pattern(i, seq);
      buf.resize(static_cast<std::size_t>(m.getEncodedSize()));
      m.encode(buf.data(), 0, static_cast<int>(buf.size()));
      if (lcm_publish(lcm, argv[3], buf.data(), static_cast<unsigned>(buf.size())) != 0) {
        std::printf("FATAL lcm_publish failed\n");
        lcm_destroy(lcm);
        return 1;
      }
      ++sent;
      if (period > Clock::duration::zero()) {
        next += period;
        std::this_thread::sleep_until(next);  // pacing the rate
      }
    }
    std::printf("done %ld\n", sent);
    std::fflush(stdout);
    lcm_destroy(lcm);
    return 0;
  }
  if (cmd == "sub" && argc == 6) {
    lcm_t* lcm = lcm_create(argv[2]);
    if (lcm == nullptr) {
      std::printf("FATAL lcm_create(%s) failed\n", argv[2]);
      return 1;
    }
    SubState st;
    // liblcm binds and joins inside lcm_subscribe, so datagrams sent after "ready" are queued.
    lcm_subscribe(lcm, argv[3], on_message, &st);
    std::printf("ready\n");
    std::fflush(stdout);
    const long count = std::atol(argv[4]);
    const auto deadline = Clock::now() + std::chrono::milliseconds(std::atol(argv[5]));
    while (st.received < count && !stdin_closed()) {
      const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now());
      if (left.count() <= 0) break;
      if (lcm_handle_timeout(lcm, static_cast<int>(std::min<long long>(left.count(), 100))) < 0) break;
    }
    std::printf(
        "SUMMARY received=%ld first=%lld last=%lld duplicates=%ld out_of_order=%ld gaps=%ld "
        "bad_content=%ld decode_errors=%ld\nEND\n",
        st.received, static_cast<long long>(st.first), static_cast<long long>(st.last), st.duplicates,
        st.out_of_order, st.gaps, st.bad, st.decode_errors);
    std::fflush(stdout);
    lcm_destroy(lcm);
    return st.received == count ? 0 : 1;
  }
  return usage();
}
