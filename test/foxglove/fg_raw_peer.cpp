// lcmx_fg_raw_peer: raw lcmx publishers of a type that is in no `.lcm` file, for the unknown-type
// test of `lcmx foxglove` (test/foxglove/server_test.cpp).
//
//   lcmx_fg_raw_peer CHANNEL RATE_HZ
//
// Publishes the same 24-byte message on two channels at RATE_HZ until stdin closes or says
// "quit": on CHANNEL from a publisher that announces no type (the server learns the fingerprint
// from a message) and on CHANNEL_T from one that announces "lcmx_test.mystery_t" with the
// fingerprint. The message: the fingerprint 0x0123456789abcdef (big-endian, as lcm-gen writes
// it), then the 16 ASCII bytes "unknown payload!". Prints "READY" once both are advertised.
// Exit: 0 on quit/EOF, 2 bad arguments, 1 an lcmx error.
#include <poll.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstring>
#include <string>
#include <thread>

#include "lcmx/core.hpp"

namespace {
// True once stdin reached EOF or carried "quit".
bool stdin_closed() {
  pollfd p{STDIN_FILENO, POLLIN, 0};
  if (::poll(&p, 1, 0) <= 0) return false;
  char c[64];
  const ssize_t n = ::read(STDIN_FILENO, c, sizeof c);
  return n <= 0 || c[0] == 'q';
}
}  // namespace

int main(int argc, char** argv) {
  if (argc != 3) {
    std::fprintf(stderr, "usage: lcmx_fg_raw_peer CHANNEL RATE_HZ\n");
    return 2;
  }
  const std::string channel = argv[1];
  const double rate = std::atof(argv[2]);
  if (!(rate > 0)) {
    std::fprintf(stderr, "lcmx_fg_raw_peer: RATE_HZ must be > 0\n");
    return 2;
  }
  constexpr std::uint64_t kFingerprint = 0x0123456789abcdefULL;
  std::byte msg[24];
  for (int i = 0; i < 8; ++i) msg[i] = static_cast<std::byte>((kFingerprint >> (56 - 8 * i)) & 0xff);
  std::memcpy(msg + 8, "unknown payload!", 16);
  try {
    auto rt = lcmx::Runtime::create();
    auto node = rt.create_node("fg_raw_peer");
    auto untyped = node.advertise_raw(channel);
    auto typed = node.advertise_raw(channel + "_T", "lcmx_test.mystery_t", static_cast<std::int64_t>(kFingerprint));
    std::printf("READY\n");
    std::fflush(stdout);
    const auto period = std::chrono::duration<double>(1.0 / rate);
    auto next = std::chrono::steady_clock::now();
    while (!stdin_closed()) {
      untyped.publish(msg);
      typed.publish(msg);
      next += std::chrono::duration_cast<std::chrono::steady_clock::duration>(period);
      std::this_thread::sleep_until(next);  // a publisher's own period, not a synchronisation
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "lcmx_fg_raw_peer: %s\n", e.what());
    return 1;
  }
  return 0;
}
