// lcmx_bridge_test_pub: a publisher the bridge tests drive message by message.
//
//   lcmx_bridge_test_pub --channel C --size BYTES --id ID [--history N]
// Advertises lcmx_examples::bench_t on C, prints "READY", then reads commands on stdin:
//   "pub N RATE"  publish N more messages (seq continues) at RATE Hz (0: back to back), then
//                 print "PUBLISHED <total>"
//   "size BYTES"  the size of the messages published from now on; prints "SIZE <bytes>"
//   "quit" or EOF exit 0.
// Messages are what lcmx_test_peer's `sub --type bench` checks: data[0..7] = ID, then byte i
// of message seq is (i * 131 + seq * 7) & 0xff.
#include <poll.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <ctime>
#include <iostream>
#include <sstream>
#include <string>
#include <thread>

#include <CLI/CLI.hpp>

#include "lcmx/core.hpp"
#include "lcmx_examples/bench_t.hpp"

int main(int argc, char** argv) {
  CLI::App app{"lcmx_bridge_test_pub"};
  std::string channel, id = "P";
  std::size_t size = 1000;
  app.add_option("--channel", channel)->required();
  app.add_option("--size", size);
  app.add_option("--id", id);
  std::uint32_t history = 0;
  std::size_t max_size = 16u << 20;
  app.add_option("--history", history, "PublisherOptions::history (keep last N)");
  app.add_option("--max-size", max_size, "largest size a 'size' command may set");
  CLI11_PARSE(app, argc, argv);
  try {
    auto rt = lcmx::Runtime::create();
    auto node = rt.create_node("bridge_test_pub");
    lcmx::PublisherOptions po;
    po.max_message_size = std::max<std::size_t>(max_size, size + 4096);
    po.history = history;
    po.shm_slots = 64;
    auto pub = node.advertise<lcmx_examples::bench_t>(channel, po);
    lcmx_examples::bench_t m{};
    m.size = static_cast<std::int32_t>(std::max<std::size_t>(size, 8));
    m.data.resize(static_cast<std::size_t>(m.size));
    std::int64_t seq = 0;
    std::cout << "READY" << std::endl;
    std::string line;
    while (std::getline(std::cin, line)) {
      std::istringstream in(line);
      std::string cmd;
      in >> cmd;
      if (cmd == "quit") break;
      if (cmd == "size") {
        std::size_t bytes = 0;
        in >> bytes;
        if (bytes < 8 || bytes + 4096 > po.max_message_size) {
          std::cout << "BAD size " << bytes << std::endl;
          continue;
        }
        m.size = static_cast<std::int32_t>(bytes);
        m.data.resize(bytes);
        std::cout << "SIZE " << bytes << std::endl;
        continue;
      }
      if (cmd != "pub") continue;
      long n = 0;
      double rate = 0;
      in >> n >> rate;
      auto next = std::chrono::steady_clock::now();
      const auto period = std::chrono::duration_cast<std::chrono::steady_clock::duration>(
          std::chrono::duration<double>(rate > 0 ? 1.0 / rate : 0.0));
      for (long k = 0; k < n; ++k, ++seq) {
        m.seq = seq;
        timespec ts{};
        clock_gettime(CLOCK_MONOTONIC, &ts);
        m.send_ns = std::int64_t{ts.tv_sec} * 1000000000 + ts.tv_nsec;
        for (std::size_t i = 8; i < m.data.size(); ++i)
          m.data[i] = static_cast<std::uint8_t>((i * 131u + static_cast<std::uint64_t>(seq) * 7u) & 0xffu);
        for (std::size_t i = 0; i < 8; ++i) m.data[i] = i < id.size() ? static_cast<std::uint8_t>(id[i]) : 0;
        pub.publish(m);
        if (rate > 0) {
          next += period;
          std::this_thread::sleep_until(next);  // pacing the rate
        }
      }
      std::cout << "PUBLISHED " << seq << std::endl;
    }
  } catch (const std::exception& e) {
    std::cout << "FATAL " << e.what() << std::endl;
    return 1;
  }
  return 0;
}
