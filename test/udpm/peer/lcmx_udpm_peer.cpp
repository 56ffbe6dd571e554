// lcmx_udpm_peer — stock liblcm on the other end of lcmx::udpm's interop tests.
//
//   lcmx_udpm_peer pub URL CHANNEL COUNT SIZE      publish COUNT test messages of SIZE bytes
//   lcmx_udpm_peer sub URL CHANNEL COUNT TIMEOUT_MS  subscribe, print "ready", then one line per
//                                                   message, then "done <n>"; exit 0 if n == COUNT
//   lcmx_udpm_peer logcheck FILE CHANNEL            count CHANNEL's events in an LCM log file;
//                                                   prints "found <n> <size of first>"; exit 0 if n > 0
//
// Test payload (shared with the Catch2 tests): bytes 0..3 = index (little-endian), byte j >= 4 =
// (j * 131 + index * 17 + 7) mod 256.
#include <lcm/eventlog.h>
#include <lcm/lcm.h>

#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>

namespace {

std::vector<std::uint8_t> make_payload(std::uint32_t index, std::size_t size) {
  std::vector<std::uint8_t> p(size);
  for (std::size_t j = 0; j < size; ++j) p[j] = static_cast<std::uint8_t>(j * 131 + index * 17 + 7);
  for (std::size_t j = 0; j < 4 && j < size; ++j) p[j] = static_cast<std::uint8_t>(index >> (8 * j));
  return p;
}

struct SubState {
  long received = 0;
};

void on_message(const lcm_recv_buf_t* rbuf, const char* channel, void* user) {
  auto* st = static_cast<SubState*>(user);
  const auto* d = static_cast<const std::uint8_t*>(rbuf->data);
  const std::size_t n = rbuf->data_size;
  std::uint32_t index = 0;
  for (std::size_t j = 0; j < 4 && j < n; ++j) index |= std::uint32_t(d[j]) << (8 * j);
  const auto expect = make_payload(index, n);
  const bool ok = n == 0 || std::memcmp(d, expect.data(), n) == 0;
  std::printf("msg %s %u %zu %s\n", channel, index, n, ok ? "ok" : "bad");
  std::fflush(stdout);
  ++st->received;
}

int usage() {
  std::fprintf(stderr,
               "usage: lcmx_udpm_peer pub URL CHANNEL COUNT SIZE\n"
               "       lcmx_udpm_peer sub URL CHANNEL COUNT TIMEOUT_MS\n"
               "       lcmx_udpm_peer logcheck FILE CHANNEL\n");
  return 2;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2) return usage();
  const std::string cmd = argv[1];
  if (cmd == "pub" && argc == 6) {
    lcm_t* lcm = lcm_create(argv[2]);
    if (lcm == nullptr) {
      std::fprintf(stderr, "lcm_create(%s) failed\n", argv[2]);
      return 1;
    }
    const long count = std::atol(argv[4]);
    const std::size_t size = std::strtoull(argv[5], nullptr, 10);
    for (long i = 0; i < count; ++i) {
      const auto p = make_payload(static_cast<std::uint32_t>(i), size);
      if (lcm_publish(lcm, argv[3], p.data(), static_cast<unsigned>(p.size())) != 0) {
        std::fprintf(stderr, "lcm_publish failed\n");
        lcm_destroy(lcm);
        return 1;
      }
    }
    std::printf("done %ld\n", count);
    std::fflush(stdout);
    lcm_destroy(lcm);
    return 0;
  }
  if (cmd == "sub" && argc == 6) {
    lcm_t* lcm = lcm_create(argv[2]);
    if (lcm == nullptr) {
      std::fprintf(stderr, "lcm_create(%s) failed\n", argv[2]);
      return 1;
    }
    SubState st;
    // lcm_subscribe binds and joins before it returns, so datagrams sent after "ready" are queued.
    lcm_subscribe(lcm, argv[3], on_message, &st);
    std::printf("ready\n");
    std::fflush(stdout);
    const long count = std::atol(argv[4]);
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(std::atol(argv[5]));
    while (st.received < count) {
      const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
      if (left.count() <= 0) break;
      if (lcm_handle_timeout(lcm, static_cast<int>(left.count())) < 0) break;
    }
    std::printf("done %ld\n", st.received);
    std::fflush(stdout);
    lcm_destroy(lcm);
    return st.received == count ? 0 : 1;
  }
  if (cmd == "logcheck" && argc == 4) {
    lcm_eventlog_t* log = lcm_eventlog_create(argv[2], "r");
    if (log == nullptr) {
      std::printf("found 0 0\n");
      return 1;
    }
    long found = 0;
    long first_size = 0;
    for (int guard = 0; guard < 1000000; ++guard) {
      lcm_eventlog_event_t* ev = lcm_eventlog_read_next_event(log);
      if (ev == nullptr) break;
      if (std::string(ev->channel, static_cast<std::size_t>(ev->channellen)) == argv[3]) {
        if (found++ == 0) first_size = ev->datalen;
      }
      lcm_eventlog_free_event(ev);
    }
    lcm_eventlog_destroy(log);
    std::printf("found %ld %ld\n", found, first_size);
    return found > 0 ? 0 : 1;
  }
  return usage();
}
