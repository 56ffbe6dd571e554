// Test helper for test/discovery: one participant (a host-scope Discovery, and a vehicle-scope
// one with --vehicle, sharing one registry slot as the runtime does). Prints
// "READY <participant id>" once it is in the registry, then with --watch "JOINED <id>",
// "UPDATED <id>" and "LEFT <id>" for the other participants it is told of (host scope) and
// "VJOINED <id>"/"VLEFT <id>" (vehicle scope), and "VSPEAKING 1"/"VSPEAKING 0" when its vehicle
// Discovery starts or stops speaking. Runs until SIGTERM (goodbye: it leaves the
// registry) or SIGKILL.
// Options: --group URL (host-local) --vehicle URL --topics a,b --period ms --lease ms
//          --dir DIR (registry directory) --host-id N --watch
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <thread>

#include <unistd.h>

#include "lcmx/discovery/discovery.hpp"
#include "lcmx/discovery/identity.hpp"
#include "registry_impl.hpp"

namespace {
volatile std::sig_atomic_t g_stop = 0;
void on_term(int) { g_stop = 1; }
}  // namespace

int main(int argc, char** argv) {
  std::string group = "udpm://239.255.76.67:7667?ttl=0", vehicle, topics, dir = "/dev/shm";
  int period = 100, lease = 1000;
  std::uint64_t host = 0;
  bool watch = false;
  for (int i = 1; i < argc; ++i) {
    const std::string k = argv[i];
    auto v = [&] { return std::string(i + 1 < argc ? argv[++i] : ""); };
    if (k == "--group") group = v();
    else if (k == "--vehicle") vehicle = v();
    else if (k == "--topics") topics = v();
    else if (k == "--period") period = std::atoi(v().c_str());
    else if (k == "--lease") lease = std::atoi(v().c_str());
    else if (k == "--dir") dir = v();
    else if (k == "--host-id") host = std::strtoull(v().c_str(), nullptr, 0);
    else if (k == "--watch") watch = true;
  }
  std::signal(SIGTERM, on_term);
  const auto id = static_cast<std::int64_t>(lcmx::discovery::random_participant_id());
  if (host == 0) host = lcmx::discovery::host_id();
  lcmx::discovery::RegistryOptions ro;
  ro.host_id = host;
  ro.group = lcmx::udpm::parse_url(group);
  ro.directory = dir;
  auto registry = lcmx::discovery::Registry::open(ro);
  auto make_beacon = [&](std::int8_t scope) {
    lcmx_msgs::beacon_t b{};
    b.participant_id = id;
    b.host_id = static_cast<std::int64_t>(host);
    b.process_name = "disc_peer";
    b.scope = scope;
    b.nodes = {"n"};
    b.num_nodes = 1;
    std::size_t pos = 0;
    while (pos < topics.size()) {
      auto comma = topics.find(',', pos);
      if (comma == std::string::npos) comma = topics.size();
      lcmx_msgs::endpoint_t e{};
      e.id = static_cast<std::int64_t>(b.endpoints.size() + 1);
      e.kind = lcmx_msgs::endpoint_t::KIND_PUBLISHER;
      e.node = "n";
      e.topic = topics.substr(pos, comma - pos);
      b.endpoints.push_back(e);
      pos = comma + 1;
    }
    b.num_endpoints = static_cast<std::int32_t>(b.endpoints.size());
    return b;
  };
  auto say = [&](const char* what, std::int64_t who) {
    if (!watch) return;
    std::printf("%s %lld\n", what, static_cast<long long>(who));
    std::fflush(stdout);
  };
  lcmx::discovery::Options o;
  o.group = lcmx::udpm::parse_url(group);
  o.period = std::chrono::milliseconds(period);
  o.lease = std::chrono::milliseconds(lease);
  o.registry = registry;
  lcmx::discovery::Discovery d(o, [&] { return make_beacon(lcmx_msgs::beacon_t::SCOPE_HOST); },
                               [&](lcmx::discovery::Change c, const lcmx::discovery::Participant& p) {
                                 say(c == lcmx::discovery::Change::joined    ? "JOINED"
                                     : c == lcmx::discovery::Change::updated ? "UPDATED"
                                                                             : "LEFT",
                                     p.beacon.participant_id);
                               });
  std::unique_ptr<lcmx::discovery::Discovery> dv;
  if (!vehicle.empty()) {
    auto ov = o;
    ov.group = lcmx::udpm::parse_url(vehicle);
    ov.scope = lcmx_msgs::beacon_t::SCOPE_VEHICLE;
    dv = std::make_unique<lcmx::discovery::Discovery>(
        ov, [&] { return make_beacon(lcmx_msgs::beacon_t::SCOPE_VEHICLE); },
        [&](lcmx::discovery::Change c, const lcmx::discovery::Participant& p) {
          say(c == lcmx::discovery::Change::left ? "VLEFT" : c == lcmx::discovery::Change::joined ? "VJOINED" : "VUPDATED",
              p.beacon.participant_id);
        });
  }
  while (registry->impl().own < 0 && !g_stop)  // polling a condition (its first publish)
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  std::printf("READY %lld\n", static_cast<long long>(id));
  std::fflush(stdout);
  // --watch: whether its vehicle Discovery speaks, each time that changes (polled: a test's
  // helper, not a synchronisation).
  bool speaking = false;
  while (!g_stop && (!watch || !dv)) ::pause();
  while (!g_stop) {
    if (dv->speaking() != speaking) {
      speaking = !speaking;
      std::printf("VSPEAKING %d\n", speaking ? 1 : 0);
      std::fflush(stdout);
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  if (dv) dv->stop();
  d.stop();
  std::printf("BYE\n");
  std::fflush(stdout);
  return 0;
}
