// RuntimeOptions::from_env (defaults overridden by LCMX_* environment variables) and check().
#include <algorithm>
#include <cerrno>
#include <cstdlib>
#include <stdexcept>
#include <string>
#include <utility>

#include "lcmx/core/error.hpp"
#include "lcmx/core/options.hpp"
#include "lcmx/discovery/identity.hpp"
#include "lcmx/udpm/config.hpp"
#include "lcmx/udpm/error.hpp"
#include "lcmx/udpm/keys.hpp"

namespace lcmx {

namespace {
long env_number(const char* name, long fallback, long min, long max) {
  const char* v = std::getenv(name);
  if (!v || !*v) return fallback;
  char* end = nullptr;
  errno = 0;
  const long n = std::strtol(v, &end, 10);
  if (errno || end == v || *end || n < min || n > max)
    throw Error(Errc::invalid_argument, std::string(name) + "='" + v + "': expected an integer in [" +
                                            std::to_string(min) + ", " + std::to_string(max) + "]");
  return n;
}
}  // namespace

RuntimeOptions RuntimeOptions::from_env() {
  RuntimeOptions o;
  if (const char* url = std::getenv("LCMX_DISCOVERY_URL"); url && *url) o.discovery_url = url;
  if (const char* url = std::getenv("LCMX_VEHICLE_URL"); url && *url) o.vehicle_url = url;
  if (const char* v = std::getenv("LCMX_VEHICLE_PUBLISH"); v && *v) {
    const std::string s = v;
    if (s == "always") o.vehicle_publish = VehiclePublish::always;
    else if (s == "on_demand") o.vehicle_publish = VehiclePublish::on_demand;
    else throw Error(Errc::invalid_argument, "LCMX_VEHICLE_PUBLISH='" + s + "': expected on_demand or always");
  }
  o.udp_limit = static_cast<std::size_t>(env_number("LCMX_UDP_LIMIT", static_cast<long>(o.udp_limit), 1, 1L << 28));
  if (const char* v = std::getenv("LCMX_MIRROR"); v && *v) {
    const std::string s = v;
    if (s == "1") {
      o.mirror = true;
    } else if (s != "0") {
      o.mirror = false;
      for (std::size_t pos = 0; pos <= s.size();) {
        const auto comma = std::min(s.find(',', pos), s.size());
        auto glob = s.substr(pos, comma - pos);
        glob.erase(0, glob.find_first_not_of(" \t"));
        glob.erase(glob.find_last_not_of(" \t") + 1);
        if (glob.empty() || glob.size() > 255)
          throw Error(Errc::invalid_argument,
                      "LCMX_MIRROR='" + s + "': expected 0, 1 or comma-separated channel patterns "
                      "(e.g. CAM_*,POSE) with no empty entry");
        o.mirror_channels.push_back(glob);
        pos = comma + 1;
      }
    }
  }
  for (auto [var, cls] : {std::pair{"LCMX_LARGE_TOPICS", TopicClass::large},
                          std::pair{"LCMX_SMALL_TOPICS", TopicClass::small}}) {
    const char* v = std::getenv(var);
    if (!v) continue;
    std::string list = v;
    for (std::size_t pos = 0; pos <= list.size();) {
      const auto comma = std::min(list.find(',', pos), list.size());
      const auto name = list.substr(pos, comma - pos);
      if (!name.empty()) {
        if (name.size() > kMaxChannelLength)
          throw Error(Errc::invalid_argument, std::string(var) + ": channel '" + name + "' is longer than 63 bytes");
        o.topic_class[name] = cls;
      }
      pos = comma + 1;
    }
  }
  o.beacon_period = std::chrono::milliseconds(env_number("LCMX_BEACON_PERIOD_MS", o.beacon_period.count(), 10, 60000));
  o.lease = std::chrono::milliseconds(env_number("LCMX_LEASE_MS", o.lease.count(), 50, 600000));
  if (const char* v = std::getenv("LCMX_VEHICLE_KEY"); v && *v) o.vehicle_key = v;
  if (const char* v = std::getenv("LCMX_HOST_KEY"); v && *v) o.host_key = v;
  o.vehicle_crypt = env_number("LCMX_VEHICLE_CRYPT", o.vehicle_crypt ? 1 : 0, 0, 1) == 1;
  o.host_crypt = env_number("LCMX_HOST_CRYPT", o.host_crypt ? 1 : 0, 0, 1) == 1;
  o.keyed_max_skew = std::chrono::seconds(env_number("LCMX_KEYED_MAX_SKEW_S", o.keyed_max_skew.count(), 0, 86400));
  return o;
}

std::string RuntimeOptions::group_url_problem(const std::string& url, bool vehicle) {
  if (vehicle && url.empty()) return {};
  try {
    const auto cfg = udpm::parse_url(url);
    if (vehicle && cfg.interface.empty()) return "'" + url + "' names no interface: add &iface=<name>";
  } catch (const std::exception& e) {
    return "'" + url + "': " + e.what();
  }
  return {};
}

std::shared_ptr<const udpm::GroupKeys> RuntimeOptions::group_keys(bool vehicle) const {
  const std::string& file = vehicle ? vehicle_key : host_key;
  const bool crypt = vehicle ? vehicle_crypt : host_crypt;
  const char* what = vehicle ? "vehicle_key (LCMX_VEHICLE_KEY)" : "host_key (LCMX_HOST_KEY)";
  if (file.empty()) {
    if (crypt)
      throw Error(Errc::invalid_argument, std::string(vehicle ? "vehicle_crypt (LCMX_VEHICLE_CRYPT)" : "host_crypt (LCMX_HOST_CRYPT)") +
                                              " asks for encryption, but no key file is named in " + what +
                                              " (write one with `lcmx keygen --group FILE`)");
    return nullptr;
  }
  try {
    auto keys = std::make_shared<udpm::GroupKeys>(udpm::read_key_file(file));
    keys->encrypt = keys->encrypt || crypt;
    return keys;
  } catch (const udpm::Error& e) {
    throw Error(Errc::invalid_argument, std::string(what) + ": " + e.what());
  }
}

udpm::GroupConfig RuntimeOptions::group_config(bool vehicle) const {
  const std::string& url = vehicle ? vehicle_url : discovery_url;
  udpm::GroupConfig cfg;
  try {
    cfg = udpm::parse_url(url);
  } catch (const std::exception& e) {
    throw Error(Errc::invalid_argument, std::string(vehicle ? "vehicle_url (LCMX_VEHICLE_URL) '" :
                                                              "discovery_url (LCMX_DISCOVERY_URL) '") +
                                            url + "': " + e.what());
  }
  cfg.keys = group_keys(vehicle);
  cfg.keyed_max_skew = keyed_max_skew;
  return cfg;
}

void RuntimeOptions::check() const {
  if (const auto why = group_url_problem(discovery_url, false); !why.empty())
    throw Error(Errc::invalid_argument, "discovery_url (LCMX_DISCOVERY_URL) " + why);
  if (const auto why = group_url_problem(vehicle_url, true); !why.empty())
    throw Error(Errc::invalid_argument, "vehicle_url (LCMX_VEHICLE_URL) " + why);
  if (lease <= beacon_period)
    throw Error(Errc::invalid_argument, "lease " + std::to_string(lease.count()) +
                                            " ms (LCMX_LEASE_MS) must be longer than beacon_period " +
                                            std::to_string(beacon_period.count()) + " ms (LCMX_BEACON_PERIOD_MS)");
  (void)group_keys(false);  // a bad key file is named now, not when the group opens
  if (!vehicle_url.empty()) (void)group_keys(true);
  try {
    (void)discovery::host_id();
  } catch (const std::invalid_argument& e) {  // a bad LCMX_HOST_ID
    throw Error(Errc::invalid_argument, e.what());
  }
}

}  // namespace lcmx
