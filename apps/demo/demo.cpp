// lcmx-demo: one publisher process with a camera (1920x1080 RGB, ~6 MB, 30 Hz) and a pose
// (100 Hz) publisher and one in-process camera subscriber; two subscriber processes (this
// binary again, --role sub). After --seconds it prints, per topic and subscriber: received
// rate, one-way latency p50/p99, lost messages, and the path, then stops everything.
// Exit code 0 when every subscriber received messages on every topic it subscribed to.
#include <CLI/CLI.hpp>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
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

#include "lcmx/core.hpp"
#include "lcmx_examples/image_t.hpp"
#include "lcmx_examples/pose_t.hpp"

namespace {

constexpr const char* kCamera = "DEMO_CAMERA";
constexpr const char* kPose = "DEMO_POSE";
constexpr const char* kStop = "DEMO_STOP";

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

  void on(const lcmx_examples::header_t& h) {
    const auto t = now_ns();
    std::lock_guard lock(mu);
    latency_us.push_back(static_cast<double>(t - h.stamp_ns) / 1000.0);
    if (first_ns == 0) first_ns = t;
    last_ns = t;
    if (last_seq >= 0 && h.seq > last_seq + 1) gaps += static_cast<std::uint64_t>(h.seq - last_seq - 1);
    last_seq = h.seq;
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
std::string result_line(const std::string& who, const char* topic, Recorder& r,
                        const lcmx::SubscriberStats& s) {
  return "RESULT " + who + " " + topic + " " + path_of(s) + " " + r.summary() + " " +
         std::to_string(s.drops);
}

// --role sub: subscribe to camera and pose until the publisher says stop.
int run_subscriber(const std::string& name, int timeout_s) {
  auto rt = lcmx::Runtime::create();
  // Two nodes, so a 6 MB image being decoded never delays a pose (each node has its own
  // executor thread; one node's callbacks run one at a time).
  auto node = rt.create_node(name);
  auto pose_node = rt.create_node(name + "_pose");
  Recorder cam, pose;
  auto cam_sub = node.subscribe<lcmx_examples::image_t>(
      kCamera, [&](const lcmx_examples::image_t& img) { cam.on(img.header); });
  auto pose_sub = pose_node.subscribe<lcmx_examples::pose_t>(
      kPose, [&](const lcmx_examples::pose_t& p) { pose.on(p.header); });
  std::mutex mu;
  std::condition_variable cv;
  bool stop = false;
  auto stop_sub = node.subscribe_raw(kStop, [&](const lcmx::RawMessage&) {
    std::lock_guard lock(mu);
    stop = true;
    cv.notify_all();
  });
  std::cout << "READY " << name << std::endl;
  {
    std::unique_lock lock(mu);
    if (!cv.wait_for(lock, std::chrono::seconds(timeout_s), [&] { return stop; }))
      std::cerr << name << ": no stop message within " << timeout_s << " s\n";
  }
  std::cout << result_line(name, kCamera, cam, cam_sub.stats()) << "\n"
            << result_line(name, kPose, pose, pose_sub.stats()) << std::endl;
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
    execl(self, self, "--role", "sub", "--name", name.c_str(), "--timeout", t.c_str(), nullptr);
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

int run_publisher(const char* self, double seconds, int width, int height, double cam_hz) {
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
      // A new frame each time, handed over by pointer: the in-process viewer gets this very
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
  const std::byte stop{0};
  stop_pub.publish(std::span<const std::byte>(&stop, 1));

  std::vector<std::string> lines;
  lines.push_back(result_line("local_viewer", kCamera, local_cam, local_sub.stats()));
  int rc = 0;
  for (auto& c : children) {
    for (int i = 0; i < 2; ++i) {
      auto line = read_line(c.out);
      if (line.rfind("RESULT", 0) == 0) lines.push_back(line);
      else rc = 1;
    }
    int status = 0;
    waitpid(c.pid, &status, 0);
    fclose(c.out);
    if (!WIFEXITED(status) || WEXITSTATUS(status) != 0) rc = 1;
  }

  std::printf("\nlcmx demo: %.0f s, camera %dx%d rgb8 (%.1f MB) at %.0f Hz, pose at 100 Hz\n", seconds,
              width, height, frame.size / 1e6, cam_hz);
  std::printf("published: camera %llu, pose %llu\n\n", static_cast<unsigned long long>(cam_pub.published()),
              static_cast<unsigned long long>(pose_pub.published()));
  std::printf("| %-12s | %-12s | %-6s | %8s | %9s | %10s | %10s | %5s | %5s |\n", "subscriber", "topic",
              "path", "received", "rate Hz", "p50 us", "p99 us", "lost", "drops");
  std::printf("|--------------|--------------|--------|----------|-----------|------------|------------|-------|-------|\n");
  for (const auto& l : lines) {
    std::istringstream in(l);
    std::string tag, who, topic, path;
    unsigned long long received = 0, lost = 0, drops = 0;
    double rate = 0, p50 = 0, p99 = 0;
    in >> tag >> who >> topic >> path >> received >> rate >> p50 >> p99 >> lost >> drops;
    if (received == 0) rc = 1;
    std::printf("| %-12s | %-12s | %-6s | %8llu | %9.1f | %10.1f | %10.1f | %5llu | %5llu |\n", who.c_str(),
                topic.c_str(), path.c_str(), received, rate, p50, p99, lost, drops);
  }
  std::printf("\nlost = gaps in sequence numbers seen by the subscriber; drops = messages lcmx\n"
              "counted as overwritten or dropped before the subscriber read them.\n");
  return rc;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"lcmx-demo: camera + pose publishers, three subscribers in three processes"};
  std::string role = "pub", name = "sub";
  double seconds = 5, cam_hz = 30;
  int width = 1920, height = 1080, timeout_s = 60;
  app.add_option("--role", role, "pub (default) or sub (started by the demo itself)")
      ->check(CLI::IsMember({"pub", "sub"}));
  app.add_option("--name", name, "subscriber name (--role sub)");
  app.add_option("--timeout", timeout_s, "subscriber: give up after this many seconds");
  app.add_option("--seconds", seconds, "how long to publish")->check(CLI::Range(0.5, 3600.0))->capture_default_str();
  app.add_option("--camera-hz", cam_hz, "camera rate")->check(CLI::Range(1.0, 200.0))->capture_default_str();
  app.add_option("--width", width, "image width")->check(CLI::Range(16, 8192))->capture_default_str();
  app.add_option("--height", height, "image height")->check(CLI::Range(16, 8192))->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  try {
    if (role == "sub") return run_subscriber(name, timeout_s);
    char self[4096] = {};
    if (readlink("/proc/self/exe", self, sizeof self - 1) <= 0) throw std::runtime_error("cannot find own executable");
    return run_publisher(self, seconds, width, height, cam_hz);
  } catch (const std::exception& e) {
    std::cerr << "lcmx-demo: " << e.what() << "\n";
    return 1;
  }
}
