// lcmx-demo internals shared by the single-host (demo.cpp) and two-chip (two_chip.cpp) modes.
#pragma once

#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "lcmx/core.hpp"
#include "lcmx_examples/image_t.hpp"
#include "lcmx_examples/pose_t.hpp"

namespace lcmx_demo {

inline constexpr const char* kCamera = "DEMO_CAMERA";
inline constexpr const char* kPose = "DEMO_POSE";
inline constexpr const char* kStop = "DEMO_STOP";

std::int64_t now_ns();  // CLOCK_MONOTONIC: one clock for every process and namespace

int run_single_host(const char* self, double seconds, int width, int height, double cam_hz);
int run_subscriber(const std::string& name, const std::vector<std::string>& topics, int timeout_s);
int run_chip_a(double seconds, int width, int height, double cam_hz);
std::pair<std::uint64_t, std::uint64_t> publish_loop(lcmx::Publisher<lcmx_examples::image_t>& cam_pub,
                                                     lcmx::Publisher<lcmx_examples::pose_t>& pose_pub,
                                                     double seconds, int width, int height, double cam_hz);
// Prints the subscriber table from "RESULT ..." lines; false if a subscriber received nothing.
bool print_results(const std::vector<std::string>& lines);

// two_chip.cpp (built when the emulation helper lcmx::test_netns is; else reports why not).
bool two_chip_available(std::string* why);
int run_two_chip(const char* self, double seconds, int width, int height, double cam_hz);

}  // namespace lcmx_demo
