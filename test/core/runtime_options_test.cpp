// RuntimeOptions::from_env (core/src/runtime_options.cpp) on its own: defaults, each variable,
// and a clear error naming a bad one.
#include <catch2/catch.hpp>
#include <spdlog/sinks/ringbuffer_sink.h>
#include <spdlog/spdlog.h>
#include <cstdlib>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "core_support.hpp"
#include "lcmx/core.hpp"
#include "lcmx/udpm/udpm.hpp"

namespace {

// Sets variables for one test and restores the previous environment afterwards.
class Env {
 public:
  Env() {
    for (const char* v : kVars) {
      const char* old = std::getenv(v);
      saved_.push_back(old ? std::optional<std::string>(old) : std::nullopt);
      ::unsetenv(v);
    }
  }
  ~Env() {
    for (std::size_t i = 0; i < std::size(kVars); ++i) {
      if (saved_[i]) ::setenv(kVars[i], saved_[i]->c_str(), 1);
      else ::unsetenv(kVars[i]);
    }
  }
  void set(const char* name, const char* value) { ::setenv(name, value, 1); }

 private:
  static constexpr const char* kVars[] = {
      "LCMX_DISCOVERY_URL", "LCMX_VEHICLE_URL", "LCMX_VEHICLE_PUBLISH", "LCMX_UDP_LIMIT",
      "LCMX_MIRROR",        "LCMX_LARGE_TOPICS", "LCMX_SMALL_TOPICS",   "LCMX_BEACON_PERIOD_MS",
      "LCMX_LEASE_MS"};
  std::vector<std::optional<std::string>> saved_;
};

std::string error_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const lcmx::Error& e) {
    CHECK(e.code() == lcmx::Errc::invalid_argument);
    return e.what();
  }
  return "";
}

}  // namespace

TEST_CASE("RuntimeOptions::from_env: no variable set gives the defaults", "[core][options]") {
  Env env;
  const auto o = lcmx::RuntimeOptions::from_env();
  const lcmx::RuntimeOptions d;
  CHECK(o.discovery_url == d.discovery_url);
  CHECK(o.vehicle_url.empty());
  CHECK(o.lease == d.lease);
  CHECK(o.beacon_period == d.beacon_period);
  CHECK(o.udp_limit == d.udp_limit);
  CHECK_FALSE(o.mirror);
  CHECK(o.topic_class.empty());
}

TEST_CASE("RuntimeOptions::from_env: every variable is read", "[core][options]") {
  Env env;
  env.set("LCMX_DISCOVERY_URL", "udpm://239.255.1.2:7000?ttl=0");
  env.set("LCMX_VEHICLE_URL", "udpm://239.255.1.3:7001?ttl=1&iface=lo");
  env.set("LCMX_VEHICLE_PUBLISH", "always");
  env.set("LCMX_UDP_LIMIT", "1000");
  env.set("LCMX_MIRROR", "CAM_*, POSE");
  env.set("LCMX_LARGE_TOPICS", "IMG,,LIDAR");
  env.set("LCMX_SMALL_TOPICS", "ODOM");
  env.set("LCMX_BEACON_PERIOD_MS", "250");
  env.set("LCMX_LEASE_MS", "900");
  const auto o = lcmx::RuntimeOptions::from_env();
  CHECK(o.discovery_url == "udpm://239.255.1.2:7000?ttl=0");
  CHECK(o.vehicle_url == "udpm://239.255.1.3:7001?ttl=1&iface=lo");
  CHECK(o.vehicle_publish == lcmx::VehiclePublish::always);
  CHECK(o.udp_limit == 1000);
  CHECK_FALSE(o.mirror);
  CHECK(o.mirror_channels == std::vector<std::string>{"CAM_*", "POSE"});
  CHECK(o.topic_class.size() == 3);
  CHECK(o.topic_class.at("IMG") == lcmx::TopicClass::large);
  CHECK(o.topic_class.at("LIDAR") == lcmx::TopicClass::large);
  CHECK(o.topic_class.at("ODOM") == lcmx::TopicClass::small);
  CHECK(o.beacon_period == std::chrono::milliseconds(250));
  CHECK(o.lease == std::chrono::milliseconds(900));
  env.set("LCMX_MIRROR", "1");
  CHECK(lcmx::RuntimeOptions::from_env().mirror);
}

TEST_CASE("RuntimeOptions::from_env: a bad value is an invalid_argument naming the variable", "[core][options]") {
  Env env;
  auto bad = [&](const char* name, const char* value) {
    Env inner;
    inner.set(name, value);
    const auto what = error_of([] { lcmx::RuntimeOptions::from_env(); });
    INFO(name << "=" << value << ": " << what);
    CHECK(what.find(name) != std::string::npos);
  };
  bad("LCMX_LEASE_MS", "abc");
  bad("LCMX_LEASE_MS", "10");  // below 50
  bad("LCMX_BEACON_PERIOD_MS", "-1");
  bad("LCMX_UDP_LIMIT", "0");
  bad("LCMX_VEHICLE_PUBLISH", "sometimes");
  bad("LCMX_MIRROR", "CAM_*,,POSE");
  bad("LCMX_LARGE_TOPICS", std::string(64, 'X').c_str());
}

// A stock LCM program (liblcm sets no IP_MULTICAST_ALL = 0) bound to the host-local group's
// port hears every group joined on its host with that port: a vehicle group on it leaks the
// other hosts' beacons and messages into such programs (seen with lcm-logger on 7667 beside a
// vehicle group on 239.255.76.68:7667). Said at start; another port is not.
TEST_CASE("a vehicle group on the host-local group's port is warned about, another port is not", "[core][options]") {
  auto sink = std::make_shared<spdlog::sinks::ringbuffer_sink_mt>(64);
  auto old = spdlog::default_logger();
  spdlog::set_default_logger(std::make_shared<spdlog::logger>("capture", sink));
  struct Restore {
    std::shared_ptr<spdlog::logger> l;
    ~Restore() { spdlog::set_default_logger(l); }
  } restore{old};
  auto warned = [&] {
    for (const auto& line : sink->last_formatted())
      if (line.find("uses the host-local group's port") != std::string::npos) return true;
    return false;
  };
  auto o = lcmx::core_test::test_options();
  const auto port = lcmx::udpm::parse_url(o.discovery_url).port;
  {
    auto same = o;
    same.vehicle_url = "udpm://239.253.250.1:" + std::to_string(port) + "?ttl=0&iface=lo";
    auto rt = lcmx::Runtime::create(same);
    CHECK(warned());
  }
  sink = std::make_shared<spdlog::sinks::ringbuffer_sink_mt>(64);
  spdlog::set_default_logger(std::make_shared<spdlog::logger>("capture2", sink));
  {
    auto other = lcmx::core_test::test_options();
    const auto p2 = lcmx::udpm::parse_url(other.discovery_url).port;
    other.vehicle_url = "udpm://239.253.250.1:" + std::to_string(p2 == 65000 ? 64999 : p2 + 1) + "?ttl=0&iface=lo";
    auto rt = lcmx::Runtime::create(other);
    CHECK_FALSE(warned());
  }
}

TEST_CASE("RuntimeOptions::check: bad groups, a short lease and a bad LCMX_HOST_ID are named, and Runtime::create refuses them",
          "[core][options]") {
  Env env;
  lcmx::RuntimeOptions good;
  CHECK_NOTHROW(good.check());
  CHECK(lcmx::RuntimeOptions::group_url_problem("", true).empty());  // no vehicle group
  CHECK(lcmx::RuntimeOptions::group_url_problem("udpm://239.255.76.68:7668?ttl=1&iface=lo", true).empty());

  auto no_iface = good;
  no_iface.vehicle_url = "udpm://239.255.76.68:7668?ttl=1";
  CHECK(error_of([&] { no_iface.check(); }) ==
        "vehicle_url (LCMX_VEHICLE_URL) 'udpm://239.255.76.68:7668?ttl=1' names no interface: add &iface=<name>");
  CHECK(error_of([&] { (void)lcmx::Runtime::create(no_iface); }).find("names no interface") != std::string::npos);

  auto bad_url = good;
  bad_url.discovery_url = "garbage";
  CHECK(error_of([&] { bad_url.check(); }).rfind("discovery_url (LCMX_DISCOVERY_URL) 'garbage': ", 0) == 0);

  auto short_lease = good;
  short_lease.lease = short_lease.beacon_period;
  CHECK(error_of([&] { short_lease.check(); }).find("(LCMX_LEASE_MS) must be longer than beacon_period") !=
        std::string::npos);

  const char* old = std::getenv("LCMX_HOST_ID");
  const std::optional<std::string> saved = old ? std::optional<std::string>(old) : std::nullopt;
  ::setenv("LCMX_HOST_ID", "chip-a", 1);
  const auto host = error_of([&] { good.check(); });
  if (saved) ::setenv("LCMX_HOST_ID", saved->c_str(), 1);
  else ::unsetenv("LCMX_HOST_ID");
  CHECK(host.find("LCMX_HOST_ID='chip-a'") != std::string::npos);
}
