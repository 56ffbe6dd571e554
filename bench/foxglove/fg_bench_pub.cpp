// lcmx_bench_foxglove_pub: the publishers of bench/foxglove/run.sh, in one process:
// --channels N pose_t channels at --rate Hz (FGB_POSE_<i>) and one 1920x1080 rgb8 image_t
// (6.2 MB) at --image-hz (FGB_CAMERA), for --seconds. Each message's publish() call is timed
// (CLOCK_MONOTONIC): printed at the end as one JSON line
// {"small_p50_us", "small_p99_us", "image_p50_us", "image_p99_us", "published"} so a run with the
// Foxglove server can be compared with one without (the publishers' latency, same run).
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <string>
#include <thread>
#include <vector>

#include "lcmx/core.hpp"
#include "lcmx_examples/image_t.hpp"
#include "lcmx_examples/pose_t.hpp"

int main(int argc, char** argv) {
  int channels = 100, seconds = 10;
  double rate = 100, image_hz = 10;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string a = argv[i];
    if (a == "--channels") channels = std::stoi(argv[i + 1]);
    else if (a == "--rate") rate = std::stod(argv[i + 1]);
    else if (a == "--image-hz") image_hz = std::stod(argv[i + 1]);
    else if (a == "--seconds") seconds = std::stoi(argv[i + 1]);
  }
  using Clock = std::chrono::steady_clock;
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("fg_bench_pub");
  std::vector<lcmx::Publisher<lcmx_examples::pose_t>> poses;
  for (int i = 0; i < channels; ++i) poses.push_back(node.advertise<lcmx_examples::pose_t>("FGB_POSE_" + std::to_string(i)));
  auto cam = node.advertise<lcmx_examples::image_t>("FGB_CAMERA");
  lcmx_examples::image_t img{};
  img.width = 1920;
  img.height = 1080;
  img.stride = 1920 * 3;
  img.encoding = "rgb8";
  img.size = img.stride * img.height;
  img.data.assign(static_cast<std::size_t>(img.size), 0x80);
  lcmx_examples::pose_t pose{};
  pose.orientation[3] = 1;
  std::printf("READY\n");
  std::fflush(stdout);
  std::vector<double> small_us, image_us;
  const auto start = Clock::now();
  const auto tick = std::chrono::duration<double>(1.0 / rate);
  const int image_every = std::max(1, static_cast<int>(rate / image_hz));
  long long published = 0;
  for (long long k = 0;; ++k) {
    const auto due = start + std::chrono::duration_cast<Clock::duration>(tick * static_cast<double>(k));
    if (due - start > std::chrono::seconds(seconds)) break;
    std::this_thread::sleep_until(due);  // a publisher's own period, not a synchronisation
    for (auto& p : poses) {
      pose.header.seq = k;
      pose.position[0] = static_cast<double>(k);
      const auto t0 = Clock::now();
      p.publish(pose);
      small_us.push_back(std::chrono::duration<double, std::micro>(Clock::now() - t0).count());
      ++published;
    }
    if (k % image_every == 0) {
      img.header.seq = k;
      const auto t0 = Clock::now();
      cam.publish(img);
      image_us.push_back(std::chrono::duration<double, std::micro>(Clock::now() - t0).count());
      ++published;
    }
  }
  auto pct = [](std::vector<double>& v, double p) {
    if (v.empty()) return 0.0;
    std::sort(v.begin(), v.end());
    return v[std::min(v.size() - 1, static_cast<std::size_t>(p / 100 * static_cast<double>(v.size())))];
  };
  std::printf("{\"small_p50_us\":%.1f,\"small_p99_us\":%.1f,\"image_p50_us\":%.1f,\"image_p99_us\":%.1f,\"published\":%lld}\n",
              pct(small_us, 50), pct(small_us, 99), pct(image_us, 50), pct(image_us, 99), published);
  return 0;
}
