#include "bridge_cmd.hpp"

#include <memory>

#include <malloc.h>
#include <signal.h>
#include <spdlog/cfg/env.h>
#include <spdlog/spdlog.h>

#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <cstdlib>
#include <iostream>
#include <map>
#include <mutex>
#include <sstream>
#include <string_view>
#include <thread>
#include <utility>

#include "lcmx/bridge/bridge.hpp"
#include "lcmx/core.hpp"
#include "log_common.hpp"
#include "status_collect.hpp"
#include "verb.hpp"

namespace lcmx::cli {
namespace {

std::string human_bytes(std::int64_t b) {
  char buf[32];
  const double v = static_cast<double>(b);
  if (b < 10 * 1024) std::snprintf(buf, sizeof buf, "%lld B", static_cast<long long>(b));
  else if (b < 10ll * 1024 * 1024) std::snprintf(buf, sizeof buf, "%.1f KiB", v / 1024);
  else if (b < 10ll * 1024 * 1024 * 1024) std::snprintf(buf, sizeof buf, "%.1f MiB", v / (1024 * 1024));
  else std::snprintf(buf, sizeof buf, "%.2f GiB", v / (1024.0 * 1024 * 1024));
  return buf;
}

std::string pad(std::string s, std::size_t w) {
  if (s.size() < w) s.append(w - s.size(), ' ');
  return s;
}

// Receive buffers stay mapped (docs/bridge.md "Receive buffers stay mapped"). ZeroMQ (libzmq
// 4.3.4, no receive allocator) mallocs a buffer for every large message it receives, and the
// bridge frees it after the copy into shared memory. glibc's defaults give such a buffer back
// to the kernel (munmap above the mmap threshold, or a trim of the arena's top) and the next
// one faults in again page by page, zeroed by the kernel: ~14 % of the receiving bridge's CPU
// at 6 MB. So allocations up to kMmapMax come from the heap and up to kKeepFree bytes of free
// heap stay mapped (after a burst, up to that much freed heap stays resident). A user who tunes
// glibc's malloc by the environment keeps their settings. Process-wide: only the daemon calls
// this, never the library (a program that embeds a Bridge chooses its own malloc settings).
void keep_receive_buffers() {
  constexpr int kMmapMax = 32 << 20;   // glibc's largest M_MMAP_THRESHOLD on 64-bit
  constexpr int kKeepFree = 64 << 20;  // M_TRIM_THRESHOLD
  const char* tunables = std::getenv("GLIBC_TUNABLES");
  if ((tunables != nullptr && std::string_view(tunables).find("glibc.malloc.") != std::string_view::npos) ||
      std::getenv("MALLOC_MMAP_THRESHOLD_") != nullptr || std::getenv("MALLOC_TRIM_THRESHOLD_") != nullptr) {
    spdlog::info("bridge: malloc tuned by the environment: receive buffers left to it");
    return;
  }
  // glibc accepts both values; a sanitizer's allocator (ASan) ignores mallopt and returns 0.
  if (::mallopt(M_MMAP_THRESHOLD, kMmapMax) != 1 || ::mallopt(M_TRIM_THRESHOLD, kKeepFree) != 1)
    spdlog::debug("bridge: mallopt refused (not glibc's allocator?): receive buffers left to it");
}

}  // namespace

Verb add_bridge(CLI::App& app, const Globals& g) {
  struct State {
    std::string config, status_url, key_prefix;
    bool check = false, key_force = false, json = false;
    int status_wait = 3000;
  };
  auto st = std::make_shared<State>();
  auto* bridge = app.add_subcommand(
      "bridge", "run this host's Message Bridge (--config FILE), or inspect bridges (status, keygen)");
  bridge->fallthrough();
  bridge->add_option("--config", st->config, "bridge config file (TOML, see docs/bridge.md)");
  bridge->add_flag("--check", st->check, "validate the config file and exit (0 ok, 2 bad)");
  bridge->add_flag("--json", st->json, "--check, status, keygen: print the result as JSON");
  auto* status = add_status_subcommand(
      *bridge, "per bridge on this host: peers, active link, bytes per link, messages/bytes/drops per channel",
      "bridges", st->status_url, st->status_wait);
  auto* keygen = bridge->add_subcommand("keygen", "write a CURVE key pair: PREFIX.key (secret, 0600), PREFIX.pub");
  keygen->add_option("--out", st->key_prefix, "file name prefix")->required();
  keygen->add_flag("--force", st->key_force, "overwrite existing files");
  return {bridge, [st, status, keygen, &g] {
            if (status->parsed())
              return bridge_status(st->status_url.empty() ? g.url : st->status_url, st->status_wait, st->json);
            if (keygen->parsed()) return bridge_keygen(st->key_prefix, st->key_force, st->json);
            if (st->config.empty()) {
              std::cerr << "lcmx bridge: --config FILE is required (or: lcmx bridge status | keygen)\n";
              return 2;
            }
            return bridge_run(st->config, st->check, st->json);
          }};
}

int bridge_run(const std::string& config_path, bool check_only, bool json) {
  bridge::Config cfg;
  try {
    cfg = bridge::load_config(config_path);
  } catch (const bridge::ConfigError& e) {
    if (check_only && json)
      std::cout << "{\"config\":" << json_str(config_path) << ",\"ok\":false,\"error\":" << json_str(e.what()) << "}"
                << std::endl;
    std::cerr << "lcmx bridge: bad config: " << e.what() << "\n";
    return 2;
  }
  if (check_only && json) {
    std::cout << "{\"config\":" << json_str(config_path) << ",\"ok\":true,\"name\":" << json_str(cfg.name)
              << ",\"channels\":" << cfg.channels.size() << ",\"peers\":" << cfg.peers.size()
              << ",\"curve\":" << (cfg.security.curve ? "true" : "false") << "}" << std::endl;
    return 0;
  }
  if (check_only) {
    std::cout << config_path << ": ok: bridge " << cfg.name << ", " << cfg.channels.size() << " channel(s), "
              << cfg.peers.size() << " peer(s)" << (cfg.security.curve ? ", CURVE" : "") << "\n";
    return 0;
  }
  spdlog::set_level(spdlog::level::info);
  spdlog::cfg::load_env_levels();
  // SIGINT/SIGTERM are taken by sigwait() below: block them before any thread starts.
  sigset_t set;
  sigemptyset(&set);
  sigaddset(&set, SIGINT);
  sigaddset(&set, SIGTERM);
  pthread_sigmask(SIG_BLOCK, &set, nullptr);
  keep_receive_buffers();
  try {
    auto options = RuntimeOptions::from_env();
    auto b = bridge::Bridge::start(std::move(cfg), options);
    std::cout << "bridge " << b.status().name << ": ready" << std::endl;
    int sig = 0;
    sigwait(&set, &sig);
    spdlog::info("bridge: signal {}: stopping", sig);
    b.stop();
  } catch (const bridge::ConfigError& e) {
    std::cerr << "lcmx bridge: bad config: " << e.what() << "\n";
    return 2;
  } catch (const std::exception& e) {
    std::cerr << "lcmx bridge: " << e.what() << "\n";
    return 1;
  }
  return 0;
}

// Status messages come from the host-local group (any process of the host can send one): every
// name in them is escaped for the terminal (safe_text.hpp).
void print_bridge_status(std::ostream& out, const lcmx_msgs::bridge_status_t& s) {
  char host[32];
  std::snprintf(host, sizeof host, "%016llx", static_cast<unsigned long long>(s.host_id));
  out << "bridge " << printable(s.name) << "  pid " << s.pid << "  host " << host << (s.curve ? "  CURVE" : "")
      << "  bad frames " << s.bad_frames << "  sent zero-copy " << s.zero_copy_sends << "  copied "
      << s.copied_sends << "  lost before sending " << s.lost_local << "\n";
  out << "  this host wants: ";
  if (s.demand.empty()) out << "-";
  for (std::size_t i = 0; i < s.demand.size(); ++i) out << (i ? ", " : "") << printable(s.demand[i]);
  out << "\n";
  for (const auto& p : s.peers) {
    out << "  peer " << printable(p.name) << "  " << (p.up ? "UP" : "DOWN") << "  active link "
        << (p.active_link.empty() ? "-" : printable(p.active_link)) << "  failovers " << p.failovers << "\n";
    out << "    " << pad("link", 10) << pad("address", 17) << pad("state", 12) << pad("sent", 13) << pad("received", 13)
        << pad("heartbeat", 11) << "rtt\n";
    for (const auto& l : p.links) {
      std::string state = l.up ? "up" : "down";
      if (l.active) state += ",active";
      const std::string age = l.heartbeat_age_ms < 0 ? "never" : std::to_string(l.heartbeat_age_ms) + " ms";
      const std::string rtt = l.rtt_us < 0 ? "-" : std::to_string(l.rtt_us) + " us";
      out << "    " << pad(printable(l.name), 10) << pad(printable(l.address), 17) << pad(state, 12) << pad(human_bytes(l.bytes_sent), 13)
          << pad(human_bytes(l.bytes_received), 13) << pad(age, 11) << rtt << "\n";
    }
    out << "    " << pad("channel", 10) << pad("sent msgs", 11) << pad("sent", 13) << pad("drops", 8) << pad("queued", 8)
        << pad("recv msgs", 11) << pad("received", 13) << "lost\n";
    for (const auto& c : p.channels)
      out << "    " << pad(printable(c.name), 10) << pad(std::to_string(c.messages_sent), 11) << pad(human_bytes(c.bytes_sent), 13)
          << pad(std::to_string(c.drops), 8) << pad(std::to_string(c.queued), 8)
          << pad(std::to_string(c.messages_received), 11) << pad(human_bytes(c.bytes_received), 13) << c.lost << "\n";
    out << "    serves: ";
    if (p.served.empty()) out << "-";
    for (std::size_t i = 0; i < p.served.size(); ++i) out << (i ? ", " : "") << printable(p.served[i]);
    out << "\n";
  }
}

std::string bridge_status_json(const lcmx_msgs::bridge_status_t& s) {
  auto strings = [](const std::vector<std::string>& v) {
    std::string o = "[";
    for (std::size_t i = 0; i < v.size(); ++i) o += (i ? "," : "") + json_str(v[i]);
    return o + "]";
  };
  auto b = [](std::int8_t v) { return v ? "true" : "false"; };
  char host[32];
  std::snprintf(host, sizeof host, "%016llx", static_cast<unsigned long long>(s.host_id));
  std::ostringstream j;
  j << "{\"name\":" << json_str(s.name) << ",\"pid\":" << s.pid << ",\"host\":\"" << host
    << "\",\"timestamp_us\":" << s.timestamp_us << ",\"curve\":" << b(s.curve) << ",\"bad_frames\":" << s.bad_frames
    << ",\"zero_copy_sends\":" << s.zero_copy_sends << ",\"copied_sends\":" << s.copied_sends
    << ",\"lost_local\":" << s.lost_local
    << ",\"demand\":" << strings(s.demand) << ",\"peers\":[";
  for (std::size_t i = 0; i < s.peers.size(); ++i) {
    const auto& p = s.peers[i];
    j << (i ? "," : "") << "{\"name\":" << json_str(p.name) << ",\"up\":" << b(p.up)
      << ",\"active_link\":" << json_str(p.active_link) << ",\"failovers\":" << p.failovers << ",\"links\":[";
    for (std::size_t k = 0; k < p.links.size(); ++k) {
      const auto& l = p.links[k];
      j << (k ? "," : "") << "{\"name\":" << json_str(l.name) << ",\"address\":" << json_str(l.address)
        << ",\"up\":" << b(l.up) << ",\"active\":" << b(l.active) << ",\"bytes_sent\":" << l.bytes_sent
        << ",\"bytes_received\":" << l.bytes_received << ",\"heartbeat_age_ms\":" << l.heartbeat_age_ms
        << ",\"rtt_us\":" << l.rtt_us << "}";
    }
    j << "],\"channels\":[";
    for (std::size_t k = 0; k < p.channels.size(); ++k) {
      const auto& c = p.channels[k];
      j << (k ? "," : "") << "{\"name\":" << json_str(c.name) << ",\"messages_sent\":" << c.messages_sent
        << ",\"bytes_sent\":" << c.bytes_sent << ",\"drops\":" << c.drops << ",\"queued\":" << c.queued
        << ",\"messages_received\":" << c.messages_received << ",\"bytes_received\":" << c.bytes_received
        << ",\"lost\":" << c.lost << "}";
    }
    j << "],\"served\":" << strings(p.served) << ",\"wanted\":" << strings(p.wanted) << "}";
  }
  j << "]}";
  return j.str();
}

int bridge_status(const std::string& url, int wait_ms, bool json) {
  return show_statuses<lcmx_msgs::bridge_status_t>("bridge", "bridges", url, bridge::kStatusChannel, wait_ms, json,
                                                   print_bridge_status, bridge_status_json);
}

int bridge_keygen(const std::string& prefix, bool force, bool json) {
  try {
    const auto keys = bridge::generate_key_pair();
    bridge::write_key_pair(prefix, keys, force);
    if (json) {
      std::cout << "{\"secret_file\":" << json_str(prefix + ".key") << ",\"public_file\":" << json_str(prefix + ".pub")
                << ",\"public_key\":" << json_str(keys.public_key) << "}" << std::endl;
      return 0;
    }
    std::cout << "wrote " << prefix << ".key (secret, mode 0600) and " << prefix << ".pub (public: " << keys.public_key
              << ")\n";
  } catch (const std::exception& e) {
    std::cerr << "lcmx bridge keygen: " << e.what() << "\n";
    return 1;
  }
  return 0;
}

}  // namespace lcmx::cli
