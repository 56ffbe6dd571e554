// The lcmx side of the DDS gateway's tests, as a process (so it can run in an emulated host):
//   lcmx_dds_lcmx_peer pub CHANNEL COUNT [SUBS]  waits for SUBS subscribers (default 1: the
//                                            gateway's export), publishes sample_t seq 0..COUNT-1
//   lcmx_dds_lcmx_peer sub CHANNEL COUNT [stay]  prints COUNT received sample_t, one line each;
//                                            with stay, then "done" and on until stdin closes
//   lcmx_dds_lcmx_peer image CHANNEL BYTES   publishes one lcmx_examples::image_t of BYTES data
// Prints "ready" when its endpoint exists; exits 0 when done, 1 on timeout (20 s).
#include <cstdio>
#include <cstdlib>
#include <iostream>
#include <mutex>
#include <condition_variable>
#include <sstream>
#include <string>

#include "lcmx/core.hpp"
#include "lcmx_ddstest/sample_t.hpp"
#include "lcmx_examples/image_t.hpp"

using namespace std::chrono_literals;

static lcmx_ddstest::sample_t make_sample(int k) {
  lcmx_ddstest::sample_t s{};
  s.seq = k;
  s.i8 = -5;
  s.i16 = -300;
  s.i32 = 70000;
  s.f = 0.5f;
  s.d = 3.25;
  s.flag = 1;
  s.b = 250;
  s.name = "from-lcmx";
  s.fixed3[0] = 0.25; s.fixed3[1] = 0.5; s.fixed3[2] = 0.75;
  s.grid[1][2] = 42;
  s.origin.x = 1.5;
  s.origin.label = "origin";
  s.corners[1].x = -4;
  s.corners[1].label = "corner";
  s.n = 3;
  s.values = {1.0, 2.0, 3.0 + k};
  s.blob = {9, 8, 7};
  s.m = 2;
  s.points.resize(2);
  s.points[0].x = 5; s.points[0].label = "a";
  s.points[1].x = 6; s.points[1].label = "b";
  s.tags = {"t1", "t2"};
  return s;
}

int main(int argc, char** argv) {
  if (argc < 4) {
    std::cerr << "usage: lcmx_dds_lcmx_peer pub|sub|image CHANNEL COUNT|BYTES\n";
    return 2;
  }
  const std::string mode = argv[1], channel = argv[2];
  const long count = std::atol(argv[3]);
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("dds_test_peer");
  if (mode == "pub") {
    auto pub = node.advertise<lcmx_ddstest::sample_t>(channel);
    std::cout << "ready" << std::endl;
    const std::size_t subs = argc > 4 ? static_cast<std::size_t>(std::atol(argv[4])) : 1;
    if (!pub.wait_for_subscribers(subs, 20000ms)) {
      std::cerr << "timeout: fewer than " << subs << " subscribers\n";
      return 1;
    }
    for (long k = 0; k < count; ++k) pub.publish(make_sample(static_cast<int>(k)));
    std::cout << "published " << count << std::endl;
    std::string line;
    std::getline(std::cin, line);  // until the test closes stdin
    return 0;
  }
  if (mode == "image") {
    auto pub = node.advertise<lcmx_examples::image_t>(channel);
    std::cout << "ready" << std::endl;
    if (!pub.wait_for_subscribers(1, 20000ms)) {
      std::cerr << "timeout: no subscriber\n";
      return 1;
    }
    lcmx_examples::image_t img{};
    img.width = 1;
    img.height = 1;
    img.encoding = "mono8";
    img.size = static_cast<int32_t>(count);
    img.stride = img.size;
    img.data.resize(static_cast<std::size_t>(count));
    for (std::size_t i = 0; i < img.data.size(); ++i) img.data[i] = static_cast<std::uint8_t>(i * 7 % 251);
    pub.publish(img);
    std::cout << "published 1 encoded=" << img.getEncodedSize() << std::endl;
    std::string line;
    std::getline(std::cin, line);
    return 0;
  }
  std::mutex mu;
  std::condition_variable cv;
  long got = 0;
  auto sub = node.subscribe<lcmx_ddstest::sample_t>(channel, [&](const lcmx_ddstest::sample_t& s) {
    std::ostringstream o;
    o << "sample seq=" << s.seq << " i8=" << int(s.i8) << " i16=" << s.i16 << " i32=" << s.i32 << " f=" << s.f
      << " d=" << s.d << " flag=" << int(s.flag) << " b=" << int(s.b) << " name=" << s.name << " fixed3=" << s.fixed3[0]
      << "," << s.fixed3[1] << "," << s.fixed3[2] << " grid12=" << s.grid[1][2] << " origin=" << s.origin.x << "/"
      << s.origin.label << " corner1=" << s.corners[1].x << "/" << s.corners[1].label << " n=" << s.n << " values=";
    for (std::size_t i = 0; i < s.values.size(); ++i) o << (i ? "," : "") << s.values[i];
    o << " blob=";
    for (std::size_t i = 0; i < s.blob.size(); ++i) o << (i ? "," : "") << int(s.blob[i]);
    o << " m=" << s.m << " points=";
    for (std::size_t i = 0; i < s.points.size(); ++i) o << (i ? "," : "") << s.points[i].x << "/" << s.points[i].label;
    o << " tags=";
    for (std::size_t i = 0; i < s.tags.size(); ++i) o << (i ? "," : "") << s.tags[i];
    std::lock_guard lock(mu);
    std::cout << o.str() << std::endl;
    ++got;
    cv.notify_all();
  });
  std::cout << "ready" << std::endl;
  std::unique_lock lock(mu);
  if (!cv.wait_for(lock, 20s, [&] { return got >= count; })) {
    std::cerr << "timeout: " << got << " of " << count << "\n";
    return 1;
  }
  if (argc > 4 && std::string(argv[4]) == "stay") {
    std::cout << "done" << std::endl;
    lock.unlock();
    std::string line;
    std::getline(std::cin, line);
  }
  return 0;
}
