// lcmx_bench_types: run-time decode (lcmx::types, from the .lcm files) vs lcm-gen's generated
// decode of the same bytes, per message type; prints the throughput ratio dynamic/generated
// (issue 11's target: >= 0.5 for the large types). Both sides measured in the same run.
//   lcmx_bench_types [--lcmtypes DIR] [--seconds S]
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>

#include "lcmx/types/types.hpp"
#include "lcmx_examples/image_t.hpp"
#include "lcmx_examples/pointcloud_t.hpp"
#include "lcmx_examples/pose_t.hpp"

namespace {

using Clock = std::chrono::steady_clock;

// Messages per second of `f` over about `seconds` (at least 3 calls).
template <class F>
double rate(double seconds, F&& f) {
  f();  // warm-up
  std::size_t n = 0;
  const auto start = Clock::now();
  double elapsed = 0;
  while (n < 3 || elapsed < seconds) {
    f();
    ++n;
    elapsed = std::chrono::duration<double>(Clock::now() - start).count();
  }
  return static_cast<double>(n) / elapsed;
}

template <class T>
void compare(const char* label, const lcmx::types::TypeRegistry& registry, const T& msg, double seconds) {
  std::vector<std::uint8_t> bytes(static_cast<std::size_t>(msg.getEncodedSize()));
  msg.encode(bytes.data(), 0, static_cast<int>(bytes.size()));
  T out;
  const double generated = rate(seconds, [&] {
    if (out.decode(bytes.data(), 0, static_cast<int>(bytes.size())) < 0) std::abort();
  });
  const double dynamic = rate(seconds, [&] {
    const lcmx::types::Value v = lcmx::types::decode(registry, bytes.data(), bytes.size());
    if (!v.is<lcmx::types::Struct>()) std::abort();
  });
  std::printf("| %-26s | %10zu | %14.0f | %14.0f | %6.2fx |\n", label, bytes.size(), generated, dynamic,
              dynamic / generated);
}

}  // namespace

int main(int argc, char** argv) {
  std::string dir = LCMX_LCMTYPES_DIR;
  double seconds = 1.0;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--help" || a == "-h") {
      std::printf("usage: lcmx_bench_types [--lcmtypes DIR] [--seconds S]\n"
                  "Decode rate of lcmx::types (run time, from .lcm) vs lcm-gen's generated code.\n");
      return 0;
    } else if (a == "--lcmtypes" && i + 1 < argc) {
      dir = argv[++i];
    } else if (a == "--seconds" && i + 1 < argc) {
      seconds = std::atof(argv[++i]);
    } else {
      std::fprintf(stderr, "lcmx_bench_types: unknown option %s (see --help)\n", a.c_str());
      return 2;
    }
  }
  const auto registry = lcmx::types::TypeRegistry::load({dir});

  lcmx_examples::image_t image{};
  image.width = 1920;
  image.height = 1080;
  image.stride = 1920 * 3;
  image.size = image.stride * image.height;  // 6 MB
  image.data.assign(static_cast<std::size_t>(image.size), 0x5a);

  lcmx_examples::pointcloud_t cloud{};
  cloud.num_fields = 4;
  cloud.fields = {"x", "y", "z", "intensity"};
  cloud.point_step = 16;
  cloud.num_points = 100000;
  cloud.size = cloud.point_step * cloud.num_points;  // 1.6 MB
  cloud.data.assign(static_cast<std::size_t>(cloud.size), 0x11);

  lcmx_examples::pose_t pose{};
  pose.header.frame_id = "map";
  pose.position[0] = 1.5;
  pose.orientation[3] = 1.0;

  std::printf("| type                       |      bytes | generated msg/s |  dynamic msg/s |  ratio |\n"
              "|---|---|---|---|---|\n");
  compare("lcmx_examples.image_t", registry, image, seconds);
  compare("lcmx_examples.pointcloud_t", registry, cloud, seconds);
  compare("lcmx_examples.pose_t", registry, pose, seconds);
  return 0;
}
