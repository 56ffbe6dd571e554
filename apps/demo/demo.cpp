// lcmx-demo. Two modes (--mode, default auto = two-chip where network namespaces can be
// created, else single-host):
//  - single-host: one publisher process with a camera (1920x1080 RGB, ~6 MB, 30 Hz) and a
//    pose (100 Hz) publisher and one in-process camera subscriber; two subscriber processes
//    (this binary again, --role sub).
//  - two-chip (two_chip.cpp): two emulated chips joined by "eth" and "pcie" links, a Message
//    Bridge on each; see two_chip.cpp.
// After --seconds it prints, per topic and subscriber: received rate, one-way latency p50/p99,
// lost messages, and the path, then stops everything.
// Exit code 0 when every subscriber received messages on every topic it subscribed to.
#include <CLI/CLI.hpp>
#include <sys/wait.h>
#include <unistd.h>

#include <pthread.h>
#include <signal.h>

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <csignal>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <iostream>
#include <mutex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "demo.hpp"
#include "lcmx/core.hpp"
#include "lcmx_examples/image_t.hpp"
#include "lcmx_examples/pose_t.hpp"

namespace lcmx_demo {

std::int64_t now_ns() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return std::int64_t{ts.tv_sec} * 1'000'000'000 + ts.tv_nsec;
}

// Per-subscriber statistics, updated on the node's executor thread.
struct Recorder {
  std::mutex mu;
  std::vector<double> latency_us;
  std::int64_t first_ns = 0, last_ns = 0;
  std::int64_t last_seq = -1;
  std::uint64_t gaps = 0;
  // Each gap: (publish stamp of the message after it, messages missing), the first 256: the
  // two-chip mode gives each to the phase it happened in (the link switch that lost them).
  std::vector<std::pair<std::int64_t, std::uint64_t>> gap_events;

  void on(const lcmx_examples::header_t& h) {
    const auto t = now_ns();
    std::lock_guard lock(mu);
    latency_us.push_back(static_cast<double>(t - h.stamp_ns) / 1000.0);
    if (first_ns == 0) first_ns = t;
    last_ns = t;
    if (last_seq >= 0 && h.seq > last_seq + 1) {
      const auto n = static_cast<std::uint64_t>(h.seq - last_seq - 1);
      gaps += n;
      if (gap_events.size() < 256) gap_events.emplace_back(h.stamp_ns, n);
    }
    last_seq = h.seq;
  }

  // "<stamp_ns>:<missing>,..." or "-".
  std::string gap_list() {
    std::lock_guard lock(mu);
    std::string s;
    for (const auto& [stamp, n] : gap_events) s += (s.empty() ? "" : ",") + std::to_string(stamp) + ":" + std::to_string(n);
    return s.empty() ? "-" : s;
  }

  // "<received> <rate_hz> <p50_us> <p99_us> <lost>"
  std::string summary() {
    std::lock_guard lock(mu);
    auto v = latency_us;
    std::sort(v.begin(), v.end());
    auto pct = [&](double p) { return v.empty() ? 0.0 : v[static_cast<std::size_t>(p * (v.size() - 1))]; };
    const double secs = static_cast<double>(last_ns - first_ns) / 1e9;
    const double rate = v.size() > 1 && secs > 0 ? static_cast<double>(v.size() - 1) / secs : 0.0;
    char buf[160];
    std::snprintf(buf, sizeof buf, "%zu %.1f %.1f %.1f %llu", v.size(), rate, pct(0.5), pct(0.99),
                  static_cast<unsigned long long>(gaps));
    return buf;
  }
};

std::string path_of(const lcmx::SubscriberStats& s) {
  std::string p;
  for (const auto& pub : s.publishers) p += (p.empty() ? "" : "+") + std::string(lcmx::to_string(pub.path));
  return p.empty() ? "-" : p;
}

// One result line: "RESULT <subscriber> <topic> <path> <received> <rate> <p50> <p99> <lost> <drops>"
// `path`: the path seen while the publisher was there (its match goes when it leaves).
std::string result_line(const std::string& who, const char* topic, Recorder& r,
                        const lcmx::SubscriberStats& s, std::string path = {}) {
  if (path.empty() || path == "-") path = path_of(s);
  return "RESULT " + who + " " + topic + " " + path + " " + r.summary() + " " +
         std::to_string(s.drops);
}

// --role sub: subscribe to the camera and/or the pose until the publisher says stop (a
// message on DEMO_STOP) or SIGTERM/SIGINT comes (main() blocked them before any thread
// started, so only this thread takes them).
int run_subscriber(const std::string& name, const std::vector<std::string>& topics, int timeout_s) {
  const bool want_cam = std::find(topics.begin(), topics.end(), "camera") != topics.end();
  const bool want_pose = std::find(topics.begin(), topics.end(), "pose") != topics.end();
  auto rt = lcmx::Runtime::create();
  // Two nodes, so a 6 MB image being decoded never delays a pose (each node has its own
  // executor thread; one node's callbacks run one at a time).
  auto node = rt.create_node(name);
  auto pose_node = rt.create_node(name + "_pose");
  Recorder cam, pose;
  lcmx::Subscriber<lcmx_examples::image_t> cam_sub;
  lcmx::Subscriber<lcmx_examples::pose_t> pose_sub;
  if (want_cam)
    cam_sub = node.subscribe<lcmx_examples::image_t>(
        kCamera, [&](const lcmx_examples::image_t& img) { cam.on(img.header); });
  if (want_pose)
    pose_sub = pose_node.subscribe<lcmx_examples::pose_t>(
        kPose, [&](const lcmx_examples::pose_t& p) { pose.on(p.header); });
  std::atomic<bool> stop{false};
  auto stop_sub = node.subscribe_raw(kStop, [&](const lcmx::RawMessage&) { stop = true; });
  std::cout << "READY " << name << std::endl;
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGTERM);
  sigaddset(&signals, SIGINT);
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(timeout_s);
  const timespec tick{0, 100'000'000};
  std::string cam_path, pose_path;  // last seen while matched
  while (!stop && sigtimedwait(&signals, nullptr, &tick) < 0) {
    if (want_cam)
      if (auto p = path_of(cam_sub.stats()); p != "-") cam_path = p;
    if (want_pose)
      if (auto p = path_of(pose_sub.stats()); p != "-") pose_path = p;
    if (std::chrono::steady_clock::now() > deadline) {
      std::cerr << name << ": no stop within " << timeout_s << " s\n";
      break;
    }
  }
  if (want_cam) std::cout << result_line(name, kCamera, cam, cam_sub.stats(), cam_path) << "\n";
  if (want_pose) std::cout << result_line(name, kPose, pose, pose_sub.stats(), pose_path) << "\n";
  // "GAPS <subscriber> <topic> <stamp_ns>:<missing>,...": where its losses were (two-chip mode).
  if (want_cam) std::cout << "GAPS " << name << " " << kCamera << " " << cam.gap_list() << "\n";
  std::cout << "END" << std::endl;
  return 0;
}

struct Child {
  pid_t pid = -1;
  FILE* out = nullptr;
};

Child spawn(const char* self, const std::string& name, int timeout_s) {
  int fds[2];
  if (pipe(fds) != 0) throw std::runtime_error("pipe failed");
  const pid_t pid = fork();
  if (pid < 0) throw std::runtime_error("fork failed");
  if (pid == 0) {
    dup2(fds[1], STDOUT_FILENO);
    close(fds[0]);
    close(fds[1]);
    const std::string t = std::to_string(timeout_s);
    execl(self, self, "--role", "sub", "--name", name.c_str(), "--timeout", t.c_str(),
          "--topics", "camera,pose", nullptr);
    _exit(127);
  }
  close(fds[1]);
  return {pid, fdopen(fds[0], "r")};
}

std::string read_line(FILE* f) {
  char buf[512];
  if (!fgets(buf, sizeof buf, f)) return {};
  std::string s(buf);
  while (!s.empty() && (s.back() == '\n' || s.back() == '\r')) s.pop_back();
  return s;
}

int run_single_host(const char* self, double seconds, int width, int height, double cam_hz) {
  const int timeout_s = static_cast<int>(seconds) + 30;
  std::vector<Child> children;
  for (const char* name : {"sub_a", "sub_b"}) children.push_back(spawn(self, name, timeout_s));
  for (auto& c : children) {
    const auto line = read_line(c.out);  // blocks until the child is subscribed (or died)
    if (line.rfind("READY", 0) != 0) {
      std::cerr << "demo: a subscriber process failed to start: \"" << line << "\"\n";
      for (auto& k : children) kill(k.pid, SIGKILL), waitpid(k.pid, nullptr, 0);
      return 1;
    }
  }

  auto rt = lcmx::Runtime::create();
  auto cam_node = rt.create_node("camera");
  auto pose_node = rt.create_node("pose");
  auto viewer_node = rt.create_node("viewer");
  lcmx::PublisherOptions cam_opts;
  cam_opts.max_message_size = 16u << 20;
  auto cam_pub = cam_node.advertise<lcmx_examples::image_t>(kCamera, cam_opts);
  auto pose_pub = pose_node.advertise<lcmx_examples::pose_t>(kPose);
  auto stop_pub = pose_node.advertise_raw(kStop);
  Recorder local_cam;
  auto local_sub = viewer_node.subscribe<lcmx_examples::image_t>(
      kCamera, [&](const std::shared_ptr<const lcmx_examples::image_t>& img) { local_cam.on(img->header); });

  const auto deadline = std::chrono::seconds(10);
  if (!cam_pub.wait_for_subscribers(3, deadline) || !pose_pub.wait_for_subscribers(2, deadline) ||
      !stop_pub.wait_for_subscribers(2, deadline)) {
    std::cerr << "demo: subscribers were not matched within 10 s (camera " << cam_pub.subscriber_count()
              << "/3, pose " << pose_pub.subscriber_count() << "/2)\n";
    for (auto& k : children) kill(k.pid, SIGKILL), waitpid(k.pid, nullptr, 0);
    return 1;
  }
  std::cerr << "demo: publishing " << width << "x" << height << " rgb8 images ("
            << (width * height * 3) / 1e6 << " MB) at " << cam_hz << " Hz and poses at 100 Hz for "
            << seconds << " s\n";

  publish_loop(cam_pub, pose_pub, seconds, width, height, cam_hz);
  const std::byte stop{0};
  stop_pub.publish(std::span<const std::byte>(&stop, 1));

  std::vector<std::string> lines;
  lines.push_back(result_line("local_viewer", kCamera, local_cam, local_sub.stats()));
  int rc = 0;
  for (auto& c : children) {
    // Its RESULT lines (and a GAPS line, not shown here) up to END; EOF without END: failed.
    for (int i = 0; i < 16; ++i) {
      auto line = read_line(c.out);
      if (line.rfind("RESULT", 0) == 0) lines.push_back(line);
      else if (line == "END") break;
      else if (line.rfind("GAPS", 0) != 0) {
        rc = 1;
        break;
      }
    }
    int status = 0;
    waitpid(c.pid, &status, 0);
    fclose(c.out);
    if (!WIFEXITED(status) || WEXITSTATUS(status) != 0) rc = 1;
  }

  std::printf("\nlcmx demo (single host): %.0f s, camera %dx%d rgb8 (%.1f MB) at %.0f Hz, pose at 100 Hz\n",
              seconds, width, height, width * height * 3 / 1e6, cam_hz);
  std::printf("published: camera %llu, pose %llu\n\n", static_cast<unsigned long long>(cam_pub.published()),
              static_cast<unsigned long long>(pose_pub.published()));
  if (!print_results(lines)) rc = 1;
  return rc;
}

// Prints the subscriber table from RESULT lines. False if a subscriber received nothing.
bool print_results(const std::vector<std::string>& lines) {
  bool ok = true;
  std::printf("| %-12s | %-12s | %-6s | %8s | %9s | %10s | %10s | %5s | %5s |\n", "subscriber", "topic",
              "path", "received", "rate Hz", "p50 us", "p99 us", "lost", "drops");
  std::printf("|--------------|--------------|--------|----------|-----------|------------|------------|-------|-------|\n");
  for (const auto& l : lines) {
    std::istringstream in(l);
    std::string tag, who, topic, path;
    unsigned long long received = 0, lost = 0, drops = 0;
    double rate = 0, p50 = 0, p99 = 0;
    in >> tag >> who >> topic >> path >> received >> rate >> p50 >> p99 >> lost >> drops;
    if (received == 0) ok = false;
    std::printf("| %-12s | %-12s | %-6s | %8llu | %9.1f | %10.1f | %10.1f | %5llu | %5llu |\n", who.c_str(),
                topic.c_str(), path.c_str(), received, rate, p50, p99, lost, drops);
  }
  std::printf("\nlost = gaps in sequence numbers seen by the subscriber; drops = messages lcmx\n"
              "counted as overwritten or dropped before the subscriber read them.\n");
  return ok;
}

// --role chip-a (two-chip mode): the camera and pose publishers of chip A. Prints PUBLISHING
// once it starts and "DONE <camera> <pose>" (messages published) at the end.
int run_chip_a(double seconds, int width, int height, double cam_hz) {
  auto rt = lcmx::Runtime::create();
  auto cam_node = rt.create_node("camera");
  auto pose_node = rt.create_node("pose");
  lcmx::PublisherOptions cam_opts;
  cam_opts.max_message_size = 16u << 20;
  auto cam_pub = cam_node.advertise<lcmx_examples::image_t>(kCamera, cam_opts);
  auto pose_pub = pose_node.advertise<lcmx_examples::pose_t>(kPose);
  if (!cam_pub.wait_for_subscribers(1, std::chrono::seconds(10))) {
    std::cerr << "chip-a: no camera subscriber within 10 s\n";
    return 1;
  }
  std::cout << "PUBLISHING" << std::endl;
  const auto [cams, poses] = publish_loop(cam_pub, pose_pub, seconds, width, height, cam_hz);
  std::cout << "DONE " << cams << " " << poses << std::endl;
  return 0;
}

// Publishes camera frames at cam_hz and poses at 100 Hz for `seconds`.
std::pair<std::uint64_t, std::uint64_t> publish_loop(lcmx::Publisher<lcmx_examples::image_t>& cam_pub,
                                                     lcmx::Publisher<lcmx_examples::pose_t>& pose_pub,
                                                     double seconds, int width, int height, double cam_hz) {
  lcmx_examples::image_t frame;
  frame.width = width;
  frame.height = height;
  frame.stride = width * 3;
  frame.encoding = "rgb8";
  frame.size = frame.stride * height;
  frame.data.assign(static_cast<std::size_t>(frame.size), 0);
  frame.header.frame_id = "camera";
  lcmx_examples::pose_t pose{};
  pose.header.frame_id = "base_link";
  pose.orientation[3] = 1.0;

  using Clock = std::chrono::steady_clock;
  const auto start = Clock::now();
  const auto cam_period = std::chrono::duration<double>(1.0 / cam_hz);
  const auto pose_period = std::chrono::milliseconds(10);
  auto next_cam = start, next_pose = start;
  std::int64_t cam_seq = 0, pose_seq = 0;
  while (Clock::now() - start < std::chrono::duration<double>(seconds)) {
    const auto now = Clock::now();
    if (now >= next_cam) {
      // A new frame each time, handed over by pointer: an in-process viewer gets this very
      // object, other processes read it from shared memory.
      auto img = std::make_shared<lcmx_examples::image_t>(frame);
      img->data[static_cast<std::size_t>(cam_seq % frame.size)] = static_cast<std::uint8_t>(cam_seq);
      img->header.seq = cam_seq++;
      img->header.stamp_ns = now_ns();
      cam_pub.publish(std::shared_ptr<const lcmx_examples::image_t>(std::move(img)));
      next_cam += std::chrono::duration_cast<Clock::duration>(cam_period);
    }
    if (now >= next_pose) {
      pose.header.seq = pose_seq++;
      pose.position[0] = 0.01 * static_cast<double>(pose_seq);
      pose.header.stamp_ns = now_ns();
      pose_pub.publish(pose);
      next_pose += pose_period;
    }
    std::this_thread::sleep_until(std::min(next_cam, next_pose));  // pacing, not synchronisation
  }
  return {cam_pub.published(), pose_pub.published()};
}

}  // namespace lcmx_demo

using namespace lcmx_demo;

int main(int argc, char** argv) {
  CLI::App app{"lcmx-demo: a camera (6 MB) and a pose publisher and their subscribers, on one host or\n"
               "on two emulated chips joined by eth and pcie links through Message Bridges"};
  std::string role = "pub", name = "sub", mode = "auto", topics = "camera,pose";
  double seconds = 0, cam_hz = 0;
  int width = 1920, height = 1080, timeout_s = 60;
  app.add_option("--mode", mode,
                 "auto (two-chip where network namespaces can be created, else single-host), "
                 "single-host or two-chip")
      ->check(CLI::IsMember({"auto", "single-host", "two-chip"}))->capture_default_str();
  app.add_option("--role", role, "pub (default: run the demo) or sub / chip-a (started by the demo itself)")
      ->check(CLI::IsMember({"pub", "sub", "chip-a"}));
  app.add_option("--name", name, "subscriber name (--role sub)");
  app.add_option("--topics", topics, "subscriber: camera,pose or one of them (--role sub)");
  app.add_option("--timeout", timeout_s, "subscriber: give up after this many seconds");
  app.add_option("--seconds", seconds, "how long to publish (default: 5 single-host, 9 two-chip: three phases of a third each, plus up to 4 s for the bridges' counts between them)")
      ->check(CLI::Range(0.5, 3600.0));
  app.add_option("--camera-hz", cam_hz, "camera rate (default: 30 single-host, 10 two-chip)")
      ->check(CLI::Range(1.0, 200.0));
  app.add_option("--width", width, "image width")->check(CLI::Range(16, 8192))->capture_default_str();
  app.add_option("--height", height, "image height")->check(CLI::Range(16, 8192))->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  try {
    if (role == "sub") {
      // Before any thread starts: SIGTERM/SIGINT are taken by run_subscriber's sigtimedwait.
      sigset_t signals;
      sigemptyset(&signals);
      sigaddset(&signals, SIGTERM);
      sigaddset(&signals, SIGINT);
      pthread_sigmask(SIG_BLOCK, &signals, nullptr);
      std::vector<std::string> list;
      std::stringstream in(topics);
      for (std::string t; std::getline(in, t, ',');) {
        if (t != "camera" && t != "pose") throw std::invalid_argument("--topics: unknown topic '" + t + "'");
        list.push_back(t);
      }
      return run_subscriber(name, list, timeout_s);
    }
    if (role == "chip-a") return run_chip_a(seconds > 0 ? seconds : 9, width, height, cam_hz > 0 ? cam_hz : 10);
    char self[4096] = {};
    if (readlink("/proc/self/exe", self, sizeof self - 1) <= 0) throw std::runtime_error("cannot find own executable");
    std::string why;
    if (mode == "two-chip" || (mode == "auto" && two_chip_available(&why)))
      return run_two_chip(self, seconds > 0 ? seconds : 9, width, height, cam_hz > 0 ? cam_hz : 10);
    if (mode == "auto")
      std::cerr << "lcmx-demo: two-chip mode not available (" << why << "): running on this host only\n";
    return run_single_host(self, seconds > 0 ? seconds : 5, width, height, cam_hz > 0 ? cam_hz : 30);
  } catch (const std::exception& e) {
    std::cerr << "lcmx-demo: " << e.what() << "\n";
    return 1;
  }
}
