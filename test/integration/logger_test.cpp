// Stock lcm-logger on LCM's default URL records lcmx's discovery on LCMX_BEACON: since v6
// (docs/discovery.md) the registry speaker's heartbeats only, a few small ones per second
// whatever the number of participants. Runs inside a network namespace the test creates, so
// LCM's default group is isolated from the host.
#include <lcm/eventlog.h>

#include "lcmx/discovery/beacon_codec.hpp"
#include "support.hpp"

using namespace lcmx::it;

namespace {

struct LogScan {
  int beacons = 0;
  bool from_peer = false;  // a heartbeat of the peer's registry speaking for it (count 1)
  std::size_t bytes = 0;   // of all LCMX_BEACON events
};

LogScan scan_log(const std::string& path, int pid, const std::string& node) {
  LogScan r;
  lcm_eventlog_t* log = lcm_eventlog_create(path.c_str(), "r");
  if (log == nullptr) return r;
  // lcm-logger flushes whole events; a torn last event just ends the scan.
  for (int guard = 0; guard < 100000; ++guard) {
    lcm_eventlog_event_t* e = lcm_eventlog_read_next_event(log);
    if (e == nullptr) break;
    if (std::string(e->channel, static_cast<std::size_t>(e->channellen)) == lcmx::discovery::kBeaconChannel) {
      ++r.beacons;
      r.bytes += static_cast<std::size_t>(e->datalen);
      auto h = lcmx::discovery::decode_host_beacon(
          std::span<const std::byte>(static_cast<const std::byte*>(e->data), static_cast<std::size_t>(e->datalen)));
      if (h && h->kind == lcmx_msgs::host_beacon_t::KIND_HEARTBEAT && h->speaker != 0 && h->count == 1)
        r.from_peer = true;
      (void)pid;
      (void)node;
    }
    lcm_eventlog_free_event(e);
  }
  lcm_eventlog_destroy(log);
  return r;
}

}  // namespace

TEST_CASE("lcm-logger on LCM's default URL records lcmx discovery heartbeats (LCMX_BEACON), a few small ones per second", "[integration][interop]") {
  Session s(60);
  Netns ns;
  REQUIRE_NETNS_OR_SKIP(ns);
  char dir_template[] = "/tmp/lcmx_it_log_XXXXXX";
  REQUIRE(::mkdtemp(dir_template) != nullptr);
  struct RemoveDir {
    std::string dir;
    ~RemoveDir() {
      std::remove((dir + "/beacons.lcmlog").c_str());
      ::rmdir(dir.c_str());
    }
  } remove_dir{dir_template};
  const std::string log = remove_dir.dir + "/beacons.lcmlog";

  // Both on the defaults: no LCM_DEFAULT_URL, no LCMX_DISCOVERY_URL (LCM's default group).
  auto& logger = s.spawn({LCMX_IP, "netns", "exec", ns.name(), LCMX_LCM_LOGGER, "-q", "-f", "--flush-interval=10", log},
                         {"LCM_DEFAULT_URL"});
  auto& peer = s.spawn({LCMX_IP, "netns", "exec", ns.name(), LCMX_TEST_PEER, "idle", "--channel",
                        unique_channel("LOGGED", 60), "--node", "logged_node", "--timeout-ms", "30000"},
                       {"LCMX_DISCOVERY_URL"});
  REQUIRE(peer.expect("READY"));
  const int peer_pid = peer.pid();
  // lcm-logger prints no ready line: the peer beacons every 100 ms; look in the log until
  // beacons of this very peer show up (deadline).
  LogScan scan;
  const bool found = wait_until(
      [&] {
        scan = scan_log(log, peer_pid, "logged_node");
        return scan.from_peer && scan.beacons >= 2;
      },
      10000ms, 50ms);
  peer.send("quit");
  CHECK(peer.wait() == 0);
  logger.signal(SIGINT);
  CHECK(logger.wait(5000ms) == 0);
  scan = scan_log(log, peer_pid, "logged_node");
  INFO("beacons in the log: " << scan.beacons);
  REQUIRE(found);
  CHECK(scan.from_peer);
  CHECK(scan.beacons >= 2);
  CHECK(scan.bytes <= static_cast<std::size_t>(scan.beacons) * 200);  // heartbeats only: no full beacons
}
