// The host registry, the speaker and the speaker protocol (docs/discovery.md): registry races,
// a dead creator, a full registry, slot reuse, torn state reads, change-log overflow, speaker
// election and death, SIGSTOP past the lease, SIGKILL seen within 100 ms, neighbours over UDP,
// observers, vehicle aggregation between emulated hosts, digest repair, the trust rules, query
// floods, and correctness at N = 200 processes (stress) and across 4 emulated hosts (multihost).
#include <arpa/inet.h>
#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <mutex>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <catch2/catch.hpp>

#include "lcmx/discovery/beacon_codec.hpp"
#include "lcmx/discovery/discovery.hpp"
#include "lcmx/discovery/identity.hpp"
#include "lcmx/test/netns.hpp"
#include "lcmx/test/process.hpp"
#include "lcmx/test/tmp_dir.hpp"
#include "registry_impl.hpp"
#include "vehicle_table.hpp"

using namespace std::chrono_literals;
using lcmx::discovery::Change;
using lcmx::discovery::Discovery;
using lcmx::discovery::Participant;
using lcmx::discovery::Registry;
using lcmx_msgs::beacon_t;
using lcmx_msgs::host_beacon_t;
using Clock = std::chrono::steady_clock;

namespace {

// A group of its own per test (salt) and process: ctest -j2 runs tests side by side.
lcmx::udpm::GroupConfig group_of(int salt) {
  const int id = static_cast<int>(::getpid()) * 64 + salt;  // salt < 64: tests in parallel never meet
  lcmx::udpm::GroupConfig g;
  g.address = "239.252." + std::to_string((id >> 8) & 0xff) + "." + std::to_string(id & 0xff);
  g.port = static_cast<std::uint16_t>(20000 + id % 40000);
  g.interface = "lo";  // the root namespace: loopback only
  return g;
}
std::string url_of(const lcmx::udpm::GroupConfig& g) {
  return "udpm://" + g.address + ":" + std::to_string(g.port) + "?ttl=0&iface=lo";
}

template <class Pred>
bool eventually(Pred pred, std::chrono::milliseconds deadline = 5000ms) {
  const auto end = Clock::now() + deadline;
  while (!pred()) {
    if (Clock::now() > end) return false;
    std::this_thread::sleep_for(1ms);  // polling a condition with a deadline
  }
  return true;
}

beacon_t beacon_of(std::int64_t id, std::uint64_t host, std::vector<std::string> topics, std::int8_t scope = beacon_t::SCOPE_HOST) {
  beacon_t b{};
  b.participant_id = id;
  b.host_id = static_cast<std::int64_t>(host);
  b.process_name = "t";
  b.scope = scope;
  for (auto& t : topics) {
    lcmx_msgs::endpoint_t e{};
    e.id = static_cast<std::int64_t>(b.endpoints.size() + 1);
    e.kind = lcmx_msgs::endpoint_t::KIND_SUBSCRIBER;
    e.node = "n";
    e.topic = t;
    b.endpoints.push_back(e);
  }
  b.num_endpoints = static_cast<std::int32_t>(b.endpoints.size());
  return b;
}

// Everything on_change tells, with the time it was told.
struct Log {
  std::mutex mu;
  std::vector<std::tuple<Change, std::int64_t, Clock::time_point, std::int64_t>> events;  // change, id, when, revision
  Discovery::ChangeFn fn() {
    return [this](Change c, const Participant& p) {
      std::lock_guard lock(mu);
      events.emplace_back(c, p.beacon.participant_id, Clock::now(), p.beacon.revision);
    };
  }
  int count(Change c, std::int64_t id) {
    std::lock_guard lock(mu);
    return static_cast<int>(std::count_if(events.begin(), events.end(), [&](auto& e) {
      return std::get<0>(e) == c && std::get<1>(e) == id;
    }));
  }
  std::optional<Clock::time_point> when(Change c, std::int64_t id) {
    std::lock_guard lock(mu);
    for (auto& e : events)
      if (std::get<0>(e) == c && std::get<1>(e) == id) return std::get<2>(e);
    return std::nullopt;
  }
};

// Removes the registry (and state files) of a test's group at the end, even on failure.
struct RegistryCleanup {
  lcmx::udpm::GroupConfig g;
  std::string dir = "/dev/shm";
  std::uint64_t host = lcmx::discovery::host_id();
  ~RegistryCleanup() { Registry::remove(host, g, dir); }
};

lcmx::discovery::Options options_of(const lcmx::udpm::GroupConfig& g) {
  lcmx::discovery::Options o;
  o.group = g;
  o.period = 50ms;
  o.lease = 500ms;
  return o;
}

std::int64_t ready_id(lcmx::test::Child& c) {
  auto line = c.expect("READY ", 10s);
  REQUIRE(line);
  return std::stoll(line->substr(6));
}

}  // namespace

TEST_CASE("registry: created once, joined, left - the last one out removes it - names clear of shm's", "[discovery][registry]") {
  const auto g = group_of(1);
  RegistryCleanup clean{g};
  const auto path = Registry::path_for(lcmx::discovery::host_id(), g);
  CHECK(std::filesystem::path(path).filename().string().rfind("lcmx_", 0) != 0);  // shm::reclaim_orphans never scans it
  {
    // Many openers at once: one file, one initialisation.
    std::vector<std::shared_ptr<Registry>> rs(8);
    std::vector<std::thread> ts;
    for (auto& r : rs) ts.emplace_back([&r, &g] {
      lcmx::discovery::RegistryOptions o;
      o.group = g;
      r = Registry::open(o);
    });
    for (auto& t : ts) t.join();
    std::set<std::uint64_t> ids;
    for (auto& r : rs) ids.insert(r->impl().header->registry_id);
    CHECK(ids.size() == 1);
    struct stat st{};
    REQUIRE(::stat(path.c_str(), &st) == 0);
    CHECK((st.st_mode & 0777) == 0666);  // several users share it
    for (std::size_t i = 0; i < rs.size(); ++i) rs[i]->impl().join(static_cast<std::int64_t>(100 + i), 1000, 100);
    CHECK(rs[0]->occupied() == 8);
    for (auto& r : rs) r->impl().leave();
    CHECK(std::filesystem::exists(path));  // still open: kept
    while (rs.size() > 1) {
      rs.pop_back();
      CHECK(std::filesystem::exists(path));
    }
    rs.clear();
    CHECK_FALSE(std::filesystem::exists(path));  // the last one to close removes it
  }
  // A registry whose users were all killed (nobody holds it open) is swept by the next
  // registry created on this host.
  {
    const auto g2 = group_of(24);
    RegistryCleanup clean2{g2};
    const auto dead = Registry::path_for(lcmx::discovery::host_id(), g2);
    const int fd = ::open(dead.c_str(), O_RDWR | O_CREAT | O_EXCL, 0666);
    REQUIRE(fd >= 0);
    ::close(fd);
    ::close(::open((dead + "_p123").c_str(), O_RDWR | O_CREAT, 0644));
    lcmx::discovery::RegistryOptions o;
    o.group = g;
    auto r = Registry::open(o);
    CHECK_FALSE(std::filesystem::exists(dead));
    CHECK_FALSE(std::filesystem::exists(dead + "_p123"));
  }
}

TEST_CASE("registry: a creator that died half-way is recovered - a foreign file is refused with a clear message", "[discovery][registry]") {
  const auto g = group_of(2);
  RegistryCleanup clean{g};
  const auto path = Registry::path_for(lcmx::discovery::host_id(), g);
  {
    // A creator died after sizing the file, before writing its version.
    const int fd = ::open(path.c_str(), O_RDWR | O_CREAT | O_EXCL, 0666);
    REQUIRE(fd >= 0);
    REQUIRE(::ftruncate(fd, 4096) == 0);
    ::close(fd);
  }
  lcmx::discovery::RegistryOptions o;
  o.group = g;
  auto r = Registry::open(o);
  CHECK(r->impl().header->version.load() == lcmx::discovery::reg::kVersion);
  r.reset();
  ::unlink(path.c_str());
  {
    const int fd = ::open(path.c_str(), O_RDWR | O_CREAT | O_EXCL, 0666);
    REQUIRE(fd >= 0);
    std::vector<char> junk(8192, 'x');
    REQUIRE(::write(fd, junk.data(), junk.size()) == static_cast<ssize_t>(junk.size()));
    ::close(fd);
  }
  try {
    Registry::open(o);
    FAIL("a foreign file was taken for a registry");
  } catch (const std::runtime_error& e) {
    CHECK(std::string(e.what()).find("is not a registry") != std::string::npos);
  }
}

TEST_CASE("registry: a full registry refuses a newcomer clearly - a freed slot is reused with a new epoch", "[discovery][registry]") {
  const auto g = group_of(3);
  RegistryCleanup clean{g};
  lcmx::discovery::RegistryOptions o;
  o.group = g;
  o.slots = 2;
  auto a = Registry::open(o), b = Registry::open(o), c = Registry::open(o);
  a->impl().join(1, 1000, 100);
  b->impl().join(2, 1000, 100);
  CHECK_THROWS_WITH(c->impl().join(3, 1000, 100), Catch::Contains("is full"));
  const auto slot = b->impl().own;
  const auto before = a->impl().slot(slot).state.load();
  b->impl().leave();
  c->impl().join(3, 1000, 100);
  CHECK(c->impl().own == slot);
  const auto after = a->impl().slot(slot).state.load();
  CHECK(lcmx::discovery::reg::epoch_of(after) == lcmx::discovery::reg::epoch_of(before) + 1);
  CHECK(lcmx::discovery::reg::state_of(after) == lcmx::discovery::reg::kLive);
  a->impl().leave();
  c->impl().leave();
}

TEST_CASE("registry: a state read torn by a writer, a corrupt or foreign-writable state file is refused", "[discovery][registry]") {
  const auto g = group_of(4);
  RegistryCleanup clean{g};
  lcmx::discovery::RegistryOptions o;
  o.group = g;
  auto w = Registry::open(o), r = Registry::open(o);
  w->impl().join(42, 1000, 100);
  const auto i = static_cast<std::uint32_t>(w->impl().own);
  const auto bytes = lcmx::discovery::encode_beacon(beacon_of(42, 1, {"A"}));
  w->impl().publish(false, bytes, 7, nullptr, 0, 0);
  auto& slot = r->impl().slot(i);
  const auto seq = slot.seq.load();
  auto st = r->impl().read_state(i, 42, seq);
  REQUIRE(st);
  CHECK(st->host == bytes);
  CHECK(st->host_struct == 7);
  // A writer between our two loads of seq: refused (the caller reads again).
  CHECK_FALSE(r->impl().read_state(i, 42, seq - 2));
  CHECK_FALSE(r->impl().read_state(i, 42, seq + 1));  // odd: being written
  // A flipped byte: the checksum refuses it.
  const auto file = w->impl().state_path;
  {
    const int fd = ::open(file.c_str(), O_RDWR);
    REQUIRE(fd >= 0);
    char x = 0;
    REQUIRE(::pread(fd, &x, 1, 70) == 1);
    x = static_cast<char>(x ^ 0x5a);
    REQUIRE(::pwrite(fd, &x, 1, 70) == 1);
    ::close(fd);
  }
  CHECK_FALSE(r->impl().read_state(i, 42, seq));
  w->impl().publish(false, bytes, 8, nullptr, 0, 0);
  REQUIRE(r->impl().read_state(i, 42, slot.seq.load()));
  ::chmod(file.c_str(), 0666);  // writable by others: anyone could have written it
  CHECK_FALSE(r->impl().read_state(i, 42, slot.seq.load()));
  w->impl().leave();
}

TEST_CASE("participants meet in the registry: join, update on a structural change only, goodbye, lease, topic filter", "[discovery]") {
  const auto g = group_of(5);
  RegistryCleanup clean{g};
  auto o = options_of(g);
  Log la;
  std::atomic<int> messages{0};
  std::atomic<bool> extra{false};
  auto b_beacon = [&] {
    auto b = beacon_of(2, lcmx::discovery::host_id(), extra ? std::vector<std::string>{"POSE", "MAP"} : std::vector<std::string>{"POSE"});
    b.endpoints[0].messages = messages.load();  // statistics: not a change
    return b;
  };
  Discovery a(o, [] { return beacon_of(1, lcmx::discovery::host_id(), {"POSE"}); }, la.fn());
  // a speaks for the registry (the speaker reads every slot: only a listener skips).
  REQUIRE(eventually([&] { return a.speaking(); }));
  Log lc;
  Discovery c(o, [] { return beacon_of(3, lcmx::discovery::host_id(), {"OTHER"}); }, lc.fn());  // shares no topic with b
  {
    Discovery b(o, b_beacon, nullptr);
    REQUIRE(eventually([&] { return la.count(Change::joined, 2) == 1; }));
    for (int k = 0; k < 5; ++k) {
      messages += 10;
      b.announce_now();
    }
    extra = true;
    b.announce_now();
    REQUIRE(eventually([&] { return la.count(Change::updated, 2) == 1; }));
    CHECK(a.participants().size() == 1);  // b; c shares no topic with a: not read, not told
    // c's passes (at least its periodic one) visit b's slot and skip it: no topic in common.
    CHECK(eventually([&] { return c.counters().registry_skipped >= 1; }, 3000ms));
  }  // b leaves
  REQUIRE(eventually([&] { return la.count(Change::left, 2) == 1; }, 1000ms));
  CHECK(la.count(Change::updated, 2) == 1);  // statistics never made an update
  CHECK(lc.count(Change::joined, 2) == 0);    // c was never told of b: no topic in common
}

TEST_CASE("a reader that fell behind the change log rescans and misses nothing", "[discovery][registry]") {
  const auto g = group_of(6);
  RegistryCleanup clean{g};
  auto o = options_of(g);
  o.period = 5000ms;  // no periodic full pass during the test: only the log or its overflow
  o.lease = 20000ms;
  Log la;
  std::atomic<int> variant{0};
  Discovery a(o, [] { return beacon_of(1, lcmx::discovery::host_id(), {"T"}); }, la.fn());
  Discovery b(o, [&] { return beacon_of(2, lcmx::discovery::host_id(), variant ? std::vector<std::string>{"T", "U"} : std::vector<std::string>{"T"}); },
              nullptr);
  REQUIRE(eventually([&] { return la.count(Change::joined, 2) == 1; }));
  // Overflow: more changes than the log holds (logged for a slot nobody uses), then b's change.
  auto r = b.registry();
  for (std::uint32_t k = 0; k < lcmx::discovery::reg::kLogSize + 100; ++k) r->impl().bump_changes(r->slots() - 1);
  variant = 1;
  b.announce_now();
  REQUIRE(eventually([&] { return la.count(Change::updated, 2) == 1; }, 3000ms));
}

TEST_CASE("a participant killed -9 is gone at every peer of its host within 100 ms - the speaker too", "[discovery][liveness]") {
  const auto g = group_of(7);
  RegistryCleanup clean{g};
  const auto url = url_of(g);
  std::vector<lcmx::test::Child> peers;
  std::vector<std::int64_t> ids;
  for (int k = 0; k < 3; ++k) {
    peers.push_back(lcmx::test::spawn({LCMX_DISCOVERY_PEER, "--group", url, "--topics", "T", "--period", "100", "--lease", "5000"}));
    ids.push_back(ready_id(peers.back()));
  }
  auto r = lcmx::discovery::Registry::open({.group = g});
  REQUIRE(eventually([&] { return r->impl().header->speaker.load() != 0; }));
  auto o = options_of(g);
  o.period = 100ms;
  o.lease = 5000ms;  // far longer than what we measure: the death is seen, not the lease
  Log la;
  Discovery a(o, [] { return beacon_of(1, lcmx::discovery::host_id(), {"T"}); }, la.fn());
  REQUIRE(eventually([&] { return a.participants().size() == 3; }));
  auto kill = [&](std::int64_t id) {
    const auto k = static_cast<std::size_t>(std::find(ids.begin(), ids.end(), id) - ids.begin());
    REQUIRE(k < peers.size());
    const auto t0 = Clock::now();
    peers[k].kill(SIGKILL);
    REQUIRE(eventually([&] { return la.count(Change::left, id) == 1; }, 3000ms));
    return *la.when(Change::left, id) - t0;
  };
  // A participant that is not the speaker.
  const auto speaker = r->impl().header->speaker.load();
  std::int64_t other = 0;
  for (auto id : ids)
    if (id != speaker && other == 0) other = id;
  const auto t1 = kill(other);
  CHECK(t1 < 100ms);
  // The speaker itself: its deputy takes over and sees it dead.
  if (speaker != 1) {
    const auto t2 = kill(speaker);
    CHECK(t2 < 100ms);
    REQUIRE(eventually([&] { return r->impl().header->speaker.load() != speaker && r->impl().header->speaker.load() != 0; }));
  }
  CHECK(a.counters().leases_expired == 0);
}

TEST_CASE("a participant stopped past its lease is gone, and back when it resumes - no one else expires", "[discovery][liveness]") {
  const auto g = group_of(8);
  RegistryCleanup clean{g};
  const auto url = url_of(g);
  auto p = lcmx::test::spawn({LCMX_DISCOVERY_PEER, "--group", url, "--topics", "T", "--period", "50", "--lease", "300"});
  const auto id = ready_id(p);
  auto q = lcmx::test::spawn({LCMX_DISCOVERY_PEER, "--group", url, "--topics", "T", "--period", "50", "--lease", "300"});
  const auto qid = ready_id(q);
  auto o = options_of(g);
  o.lease = 300ms;
  Log la;
  Discovery a(o, [] { return beacon_of(1, lcmx::discovery::host_id(), {"T"}); }, la.fn());
  REQUIRE(eventually([&] { return a.participants().size() == 2; }));
  const auto t0 = Clock::now();
  p.kill(SIGSTOP);
  REQUIRE(eventually([&] { return la.count(Change::left, id) == 1; }, 3000ms));
  CHECK(*la.when(Change::left, id) - t0 >= 250ms);  // its lease, not a death
  p.kill(SIGCONT);
  REQUIRE(eventually([&] { return la.count(Change::joined, id) == 2; }, 3000ms));
  CHECK(la.count(Change::left, qid) == 0);
}

TEST_CASE("neighbours (another /dev/shm on this network namespace) meet over UDP through their speakers", "[discovery][neighbour]") {
  const auto g = group_of(9);
  lcmx::test::TmpDir other("lcmx_neigh");
  RegistryCleanup clean{g};
  RegistryCleanup clean_b{g, other.path, 0x5151};
  auto o = options_of(g);
  Log la, lb;
  Discovery a(o, [] { return beacon_of(1, lcmx::discovery::host_id(), {"T"}); }, la.fn());
  auto ob = o;
  ob.registry = Registry::open({.host_id = 0x5151, .group = g, .directory = other.path});
  Discovery b(ob, [] { return beacon_of(2, 0x5151, {"T"}); }, lb.fn());
  REQUIRE(eventually([&] { return la.count(Change::joined, 2) == 1 && lb.count(Change::joined, 1) == 1; }));
  REQUIRE(a.speaking());
  REQUIRE(b.speaking());
  b.stop();  // goodbye through b's speaker (b itself)
  REQUIRE(eventually([&] { return la.count(Change::left, 2) == 1; }, 2000ms));
}

TEST_CASE("observers see every participant of the host with fresh statistics, and are never listed", "[discovery][observer]") {
  const auto g = group_of(10);
  RegistryCleanup clean{g};
  auto o = options_of(g);
  std::atomic<int> messages{0};
  Log la;
  Discovery a(o, [&] {
    auto b = beacon_of(1, lcmx::discovery::host_id(), {"T"});
    b.endpoints[0].messages = messages.load();
    return b;
  }, la.fn());
  Discovery b(o, [] { return beacon_of(2, lcmx::discovery::host_id(), {"U"}); }, nullptr);
  auto ob = o;
  ob.observer = true;
  Discovery observer(ob, nullptr, nullptr);
  observer.query();
  REQUIRE(eventually([&] { return observer.participants().size() == 2; }));
  messages = 77;
  REQUIRE(eventually([&] {
    for (const auto& p : observer.participants())
      if (p.beacon.participant_id == 1 && p.beacon.endpoints.size() == 1 && p.beacon.endpoints[0].messages == 77) return true;
    return false;
  }, 3000ms));
  CHECK(la.count(Change::joined, 2) == 0);  // no topic in common
  CHECK(a.participants().empty());          // the observer is not listed
}

namespace {

// One emulated host inside this test process: its own registry (host id, directory) and, per
// participant, a host-scope and a vehicle-scope Discovery sharing it (as the runtime does).
struct FakeHost {
  std::uint64_t host;
  lcmx::udpm::GroupConfig local, vehicle;
  lcmx::test::TmpDir dir{"lcmx_vh"};
  std::shared_ptr<Registry> registry;
  struct P {
    std::unique_ptr<Discovery> h, v;
    std::shared_ptr<Log> vl = std::make_shared<Log>();  // what its vehicle scope tells
  };
  std::vector<P> ps;
  Log vlog;
  FakeHost(std::uint64_t h, lcmx::udpm::GroupConfig l, lcmx::udpm::GroupConfig v) : host(h), local(l), vehicle(v) {
    registry = Registry::open({.host_id = h, .group = l, .directory = dir.path});
  }
  ~FakeHost() {
    ps.clear();
    Registry::remove(host, local, dir.path);
  }
  Log hlog;  // what the host scope tells
  // `edit` (if any) changes both beacons of the participant each time they are built.
  void add(std::int64_t id, std::vector<std::string> topics, std::function<void(beacon_t&)> edit = nullptr) {
    lcmx::discovery::Options o;
    o.group = local;
    o.period = 50ms;
    o.lease = 500ms;
    o.registry = registry;
    // A registry object per participant, as per process (an OFD lock belongs to its open file).
    o.registry = Registry::open({.host_id = host, .group = local, .directory = dir.path});
    P p;
    p.h = std::make_unique<Discovery>(
        o,
        [=, this] {
          auto b = beacon_of(id, host, topics);
          if (edit) edit(b);
          return b;
        },
        hlog.fn());
    o.group = vehicle;
    o.scope = beacon_t::SCOPE_VEHICLE;
    p.v = std::make_unique<Discovery>(
        o,
        [=, this] {
          auto b = beacon_of(id, host, topics, beacon_t::SCOPE_VEHICLE);
          if (edit) edit(b);
          return b;
        },
        [all = vlog.fn(), log = p.vl](Change c, const Participant& q) {  // (keeps its log alive)
          all(c, q);
          log->fn()(c, q);
        });
    ps.push_back(std::move(p));
  }
};

lcmx::udpm::Message message_of(const std::vector<std::byte>& bytes, const char* ip) {
  lcmx::udpm::Message m{lcmx::discovery::kBeaconChannel, bytes, {}, 0, 0, nullptr};
  m.source.address_be = ::inet_addr(ip);
  m.source.port_be = htons(7000);
  return m;
}

host_beacon_t heartbeat_of(std::int64_t host, std::map<std::int64_t, std::int64_t> set) {
  host_beacon_t h{};
  h.version = lcmx::discovery::kHostBeaconVersion;
  h.kind = host_beacon_t::KIND_HEARTBEAT;
  h.scope = beacon_t::SCOPE_VEHICLE;
  h.host_id = host;
  h.registry_id = 99;
  h.speaker = 1;
  h.lease_ms = 300;
  std::uint64_t d = 1469598103934665603ull;
  for (auto [id, rev] : set) {
    std::int64_t v[2] = {id, rev};
    d = lcmx::discovery::reg::fnv1a(std::as_bytes(std::span(v)), d);
  }
  h.digest = static_cast<std::int64_t>(d);
  h.count = static_cast<std::int32_t>(set.size());
  return h;
}

}  // namespace

TEST_CASE("vehicle scope: each host's speaker speaks for its participants - records, goodbyes, index - the others "
          "follow its vehicle table and are told only what shares a topic with them",
          "[discovery][vehicle]") {
  const auto v = group_of(11);
  FakeHost a(0xa1, group_of(12), v), b(0xb2, group_of(13), v);
  a.add(11, {"X"});
  a.add(12, {"Y"});
  b.add(21, {"X"});
  b.add(22, {"X"});
  auto info = [&] {
    std::string t;
    for (auto* h : {&a, &b})
      for (auto& p : h->ps) {
        const auto c = p.v->counters();
        t += "speaking=" + std::to_string(p.v->speaking()) + " listening=" + std::to_string(p.v->listening()) +
             " sent=" + std::to_string(c.beacons_sent) + " recv=" + std::to_string(c.beacons_received) +
             " table_reads=" + std::to_string(c.table_reads) + " table_records=" + std::to_string(c.table_records) +
             " skipped=" + std::to_string(c.table_skipped) + " forged=" + std::to_string(c.forged) +
             " malformed=" + std::to_string(c.malformed) + " requests_sent=" + std::to_string(c.requests_sent) + "\n";
      }
    return t;
  };
  // One speaker per host and group; the other participant follows.
  auto roles = [](FakeHost& h) {
    return eventually([&] { return h.ps[0].v->speaking() != h.ps[1].v->speaking(); });
  };
  REQUIRE(roles(a));
  REQUIRE(roles(b));
  auto& bs = b.ps[0].v->speaking() ? b.ps[0] : b.ps[1];
  auto& bf = &bs == &b.ps[0] ? b.ps[1] : b.ps[0];
  auto& as = a.ps[0].v->speaking() ? a.ps[0] : a.ps[1];
  auto& af = &as == &a.ps[0] ? a.ps[1] : a.ps[0];
  const std::int64_t af_id = &af == &a.ps[0] ? 11 : 12;
  // b's speaker hears both of a's; b's follower (topic X) is told of 11 (X) from the table, not 12 (Y).
  const bool met = eventually([&] {
    return bs.vl->count(Change::joined, 11) == 1 && bs.vl->count(Change::joined, 12) == 1 &&
           bf.vl->count(Change::joined, 11) == 1;
  });
  INFO(info());
  REQUIRE(met);
  // a's speaker hears both of b's; a's follower too if it is 11 (X), none if it is 12 (Y).
  REQUIRE(eventually([&] {
    return as.vl->count(Change::joined, 21) == 1 && as.vl->count(Change::joined, 22) == 1 &&
           af.vl->count(Change::joined, 21) == (af_id == 11 ? 1 : 0);
  }));
  CHECK(!bf.v->listening());
  CHECK(!af.v->listening());
  CHECK(bs.v->listening());
  // Steady state: the hosts' digests agree, no request and no record goes out any more.
  auto answered = [&] {
    std::uint64_t n = 0;
    for (auto* h : {&a, &b})
      for (auto& p : h->ps) n += p.v->counters().requests_answered;
    return n;
  };
  std::this_thread::sleep_for(300ms);  // let the join's index and records settle (6 periods)
  const auto settled = answered();
  std::this_thread::sleep_for(500ms);  // 10 periods: a digest that disagreed would ask every 2
  CHECK(answered() == settled);
  CHECK(bf.vl->count(Change::joined, 12) == 0);  // not its topic: skipped in the table
  CHECK(bf.v->counters().table_skipped >= 1);
  CHECK(bf.v->counters().requests_sent == 0);  // a follower never asks the LAN
  CHECK(af.v->counters().requests_sent == 0);
  // a's follower leaves: b's speaker is told by a's speaker, b's follower by the table if it knew it.
  const bool knew = af_id == 11;
  af.v->stop();
  af.h->stop();
  REQUIRE(eventually([&] { return bs.vl->count(Change::left, af_id) == 1; }, 2000ms));
  if (knew) REQUIRE(eventually([&] { return bf.vl->count(Change::left, af_id) == 1; }, 2000ms));
  CHECK(bs.v->counters().forged == 0);
  CHECK(bf.v->counters().malformed == 0);
}

// A stopped speaker (SIGSTOP) holds its lock: before, its host went silent on the vehicle group
// and other hosts dropped every participant of it after the host's lease.
TEST_CASE("vehicle scope: while a host's speaker is stopped another participant speaks for the host - other hosts drop "
          "only the stopped one, and it stands down when the speaker resumes",
          "[discovery][vehicle][liveness]") {
  const auto v = group_of(54), la = group_of(55);
  lcmx::test::TmpDir dir("lcmx_act");
  RegistryCleanup clean_a{la, dir.path, 0xa1};
  FakeHost b(0xb2, group_of(56), v);
  b.add(21, {"X"});
  const std::vector<std::string> peer = {LCMX_DISCOVERY_PEER, "--group", url_of(la), "--vehicle", url_of(v), "--dir",
                                         dir.path, "--host-id", "0xa1", "--period", "50", "--lease", "500",
                                         "--topics", "X", "--watch"};
  auto speaker = lcmx::test::spawn(peer);
  const auto sid = ready_id(speaker);
  REQUIRE(speaker.expect("VSPEAKING 1", 5s));
  auto other = lcmx::test::spawn(peer);
  const auto oid = ready_id(other);
  REQUIRE(eventually([&] { return b.vlog.count(Change::joined, sid) == 1 && b.vlog.count(Change::joined, oid) == 1; }));

  speaker.kill(SIGSTOP);
  // The other participant takes over within half the lease (250 ms) and a period or two ...
  const auto acted = other.expect("VSPEAKING 1", 3s);
  CHECK(acted);
  // ... so host b is told the stopped one left (its lease ran out), not the host.
  REQUIRE(eventually([&] { return b.vlog.count(Change::left, sid) == 1; }, 3000ms));
  // For three more leases the other participant is never dropped (before: host a expired at b
  // one lease after the stop, and with it this participant).
  CHECK_FALSE(eventually([&] { return b.vlog.count(Change::left, oid) > 0; }, 1500ms));

  speaker.kill(SIGCONT);
  // The speaker resumes; the acting one hears it and stands down; the resumed one is back at b.
  CHECK(other.expect("VSPEAKING 0", 3s));
  REQUIRE(eventually([&] { return b.vlog.count(Change::joined, sid) == 2; }, 3000ms));
  CHECK(b.vlog.count(Change::left, oid) == 0);
  CHECK(b.vlog.count(Change::left, sid) == 1);
}

// The vehicle table's file for host `host` (docs/discovery.md "Vehicle table").
std::string table_path(const FakeHost& h) {
  std::ostringstream s;
  s << Registry::path_for(h.host, h.local, h.dir.path) << "_pv" << std::hex << lcmx::discovery::reg::group_hash(h.vehicle);
  return s.str();
}

TEST_CASE("vehicle scope: a process that starts later takes the other hosts' records from its host's vehicle table - "
          "it asks the LAN nothing",
          "[discovery][vehicle]") {
  const auto v = group_of(46);
  FakeHost a(0xa5, group_of(47), v), b(0xb6, group_of(48), v);
  a.add(51, {"X"});
  a.add(52, {"Y"});
  b.add(61, {"Z"});
  REQUIRE(eventually([&] { return b.vlog.count(Change::joined, 51) == 1 && b.vlog.count(Change::joined, 52) == 1; }));
  REQUIRE(eventually([&] { return b.ps[0].v->complete(); }));
  REQUIRE(eventually([&] { return std::filesystem::exists(table_path(b)); }));
  auto answered = [&] {
    std::uint64_t n = 0;
    for (auto& p : a.ps) n += p.v->counters().requests_answered;
    return n;
  };
  const auto before = answered();
  b.add(62, {"X"});
  auto& late = *b.ps[1].v;
  // From the table: 51 (its topic X), not 52 (Y); complete as the table's writer is.
  REQUIRE(eventually([&] { return b.ps[1].vl->count(Change::joined, 51) == 1 && late.complete(); }, 3000ms));
  CHECK(!late.speaking());
  CHECK(!late.listening());
  CHECK(late.counters().table_records == 1);
  CHECK(late.counters().table_skipped >= 1);
  CHECK(b.ps[1].vl->count(Change::joined, 52) == 0);
  // Nobody asked a for anything (without the table it asks for a's records).
  std::this_thread::sleep_for(200ms);  // 4 periods: a request would have gone by now
  CHECK(answered() == before);
  CHECK(late.counters().requests_sent == 0);
  CHECK(late.counters().forged == 0);
}

TEST_CASE("vehicle scope: a vehicle table writable by others, of another owner, or of a writer not in the registry is "
          "not followed - a stale one is, until the follower listens itself",
          "[discovery][vehicle][hostile]") {
  namespace table = lcmx::discovery::table;
  const auto v = group_of(49);
  FakeHost c(0xc7, group_of(50), v);
  // A live slot of c's registry, as the writer a forger would name; it holds c's vehicle
  // speaker and acting locks (it writes nothing), so c's participants follow the table.
  auto writer_reg = Registry::open({.host_id = c.host, .group = c.local, .directory = c.dir.path});
  writer_reg->impl().join(777, 500, 50);
  const auto bits = static_cast<off_t>(lcmx::discovery::reg::group_hash(v) & ((std::uint64_t{1} << 40) - 1));
  REQUIRE(writer_reg->impl().try_lock(lcmx::discovery::reg::kLockVehicle + bits));
  REQUIRE(writer_reg->impl().try_lock(lcmx::discovery::reg::kLockVehicleActing + bits));
  // A record of participant 999 of a host 0xa5 that does not exist: known only from the table.
  std::uint64_t generation = 0;
  auto write = [&](std::int64_t writer, std::int64_t written_ns, mode_t mode, uid_t owner) {
    table::Content content;
    content.writer = writer;
    content.complete = true;
    table::Content::HostEntry h;
    h.host.host_id = 0xa5;
    h.host.address = ::inet_addr("10.251.0.1");
    h.host.registry_id = 5;
    h.host.speaker = 999;
    h.host.lease_ms = 500;
    auto b = beacon_of(999, 0xa5, {"X"}, beacon_t::SCOPE_VEHICLE);
    b.version = lcmx::discovery::kBeaconVersion;
    b.revision = 1;
    table::Content::Entry e;
    e.participant_id = 999;
    e.revision = 1;
    e.topics.add("X");
    e.bytes = lcmx::discovery::encode_beacon(b);
    h.records.push_back(e);
    h.host.listed_digest = 12345;
    content.hosts.push_back(h);
    auto bytes = table::encode(content, c.host, ++generation);
    std::memcpy(bytes.data() + offsetof(table::Header, written_ns), &written_ns, sizeof written_ns);
    const auto path = table_path(c);
    const auto tmp = path + ".t";
    {
      std::ofstream f(tmp, std::ios::binary | std::ios::trunc);
      f.write(reinterpret_cast<const char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
    }
    REQUIRE(::chmod(tmp.c_str(), mode) == 0);
    REQUIRE(::chown(tmp.c_str(), owner, static_cast<gid_t>(-1)) == 0);
    REQUIRE(std::filesystem::exists(tmp));
    std::filesystem::rename(tmp, path);  // as a speaker does: readers see the old file or the new one
  };
  auto now_ns = [] { return lcmx::discovery::reg::now_ns(); };
  const uid_t me = ::getuid();
  auto refused_by = [&](std::size_t k) { return c.ps[k].v->counters().tables_refused; };
  write(777, now_ns(), 0666, me);  // writable by others
  c.add(71, {"X"});
  REQUIRE(eventually([&] { return refused_by(0) >= 1; }));
  write(778, now_ns(), 0644, me);  // a writer that holds no slot
  c.add(72, {"X"});
  REQUIRE(eventually([&] { return refused_by(1) >= 1; }));
  write(777, now_ns(), 0644, me == 0 ? 65534 : me + 1);  // owned by another uid than the writer's slot names
  c.add(73, {"X"});
  if (me == 0) REQUIRE(eventually([&] { return refused_by(2) >= 1; }));
  CHECK(c.vlog.count(Change::joined, 999) == 0);
  for (auto& p : c.ps) CHECK(!p.v->speaking());
  // The same file, trusted (current or not: a stopped speaker's table is still the best there is): followed.
  write(777, now_ns() - 2'000'000'000, 0644, me);
  c.add(74, {"X"});
  REQUIRE(eventually([&] { return c.ps[3].vl->count(Change::joined, 999) == 1; }));
  CHECK(c.ps[3].v->counters().table_records == 1);
  CHECK(c.ps[3].v->counters().forged == 0);
  // Stale for two acting periods (the speaker neither writes it nor can anyone act): the
  // followers listen to the group themselves.
  REQUIRE(eventually([&] { return c.ps[3].v->listening(); }, 3000ms));
  CHECK(!c.ps[3].v->speaking());
  c.ps.clear();
  writer_reg.reset();
}

TEST_CASE("vehicle scope: a local match sends no vehicle record again, a match across hosts does",
          "[discovery][vehicle]") {
  const auto v = group_of(27);
  FakeHost a(0xa7, group_of(28), v), b(0xb8, group_of(29), v);
  auto stage = std::make_shared<std::atomic<int>>(0);
  auto match = [](std::int64_t participant, const char* path) {
    lcmx_msgs::match_t m{};
    m.publisher_participant = participant;
    m.publisher_endpoint = 1;
    m.path = path;
    return m;
  };
  // Participant 71's subscriber of X: at stage 1 matched to 72 on its own host (shm), at stage 2
  // to 81 on host b too (udp).
  a.add(71, {"X"}, [=](beacon_t& bc) {
    auto& e = bc.endpoints.at(0);
    if (stage->load() >= 1) e.matches.push_back(match(72, "shm"));
    if (stage->load() >= 2) e.matches.push_back(match(81, "udp"));
    e.num_matches = static_cast<std::int32_t>(e.matches.size());
  });
  a.add(72, {"X"});  // shares the topic: its host scope is told of 71's changes
  b.add(81, {"X"});
  REQUIRE(eventually([&] { return b.vlog.count(Change::joined, 71) == 1 && b.vlog.count(Change::joined, 72) == 1; }));
  auto records = [&] { return b.ps[0].v->counters().beacons_received; };
  std::this_thread::sleep_for(300ms);  // let the join's records settle (6 periods)
  const auto settled = records();
  // The local match: host a's other participant is told (host scope), host b gets nothing.
  const int host_updates = a.hlog.count(Change::updated, 71);
  stage->store(1);
  REQUIRE(eventually([&] { return a.hlog.count(Change::updated, 71) > host_updates; }));
  std::this_thread::sleep_for(300ms);  // 10 record windows (30 ms) for a record that should not go
  CHECK(records() == settled);
  CHECK(b.vlog.count(Change::updated, 71) == 0);
  // The match across hosts: host b gets the record.
  stage->store(2);
  REQUIRE(eventually([&] { return b.vlog.count(Change::updated, 71) == 1; }));
  CHECK(records() > settled);
}

namespace {
// A vehicle-scope Discovery's options for a receiver that hears the group only through what a
// test hands it (Discovery::deliver, from a VehiclePump), with a registry of host `host`.
lcmx::discovery::Options fed_vehicle_options(const lcmx::udpm::GroupConfig& v, std::uint64_t host,
                                             const lcmx::udpm::GroupConfig& local, const std::string& dir) {
  lcmx::discovery::Options o;
  o.group = v;
  o.scope = beacon_t::SCOPE_VEHICLE;
  o.period = 50ms;
  o.lease = 500ms;
  o.shared_group = std::make_shared<lcmx::udpm::Group>(lcmx::udpm::Group::open(v));
  o.registry = Registry::open({.host_id = host, .group = local, .directory = dir});
  return o;
}

// A vehicle-scope observer on `v` whose datagrams the test hands to it (Discovery::deliver).
lcmx::discovery::Options fed_observer_options(const lcmx::udpm::GroupConfig& v) {
  lcmx::discovery::Options o;
  o.group = v;
  o.scope = beacon_t::SCOPE_VEHICLE;
  o.observer = true;
  o.shared_group = std::make_shared<lcmx::udpm::Group>(lcmx::udpm::Group::open(v));
  return o;
}

// A vehicle record of participant `id` of `host`, subscribing to `topic`, as that host's
// speaker at 10.9.0.1 sends it.
beacon_t remote_record(std::int64_t id, std::uint64_t host, const std::string& topic, std::int64_t revision = 1) {
  auto b = beacon_of(id, host, {topic}, beacon_t::SCOPE_VEHICLE);
  b.version = lcmx::discovery::kBeaconVersion;
  b.revision = revision;
  b.vehicle_source = "10.9.0.1:7668";
  return b;
}

// A watcher's decoding of records on a group: keeps each record as heard (lcm-gen's bytes),
// so a batch compressed against one of them (batch_base) decodes too. One thread.
class HeardRecords {
 public:
  std::optional<lcmx_msgs::records_t> batch(std::span<const std::byte> bytes) {
    const auto [id, revision] = lcmx::discovery::batch_base(bytes);
    const auto base = held_.find({id, revision});
    auto r = lcmx::discovery::decode_batch(bytes, nullptr,
                                           id != 0 && base != held_.end() ? std::span<const std::byte>(base->second)
                                                                          : std::span<const std::byte>{});
    if (r) keep(r->records);
    return r;
  }
  std::optional<std::vector<beacon_t>> any(std::span<const std::byte> bytes) {
    const auto fp = lcmx::discovery::fingerprint_of(bytes);
    if (fp == lcmx_msgs::records_t::getHash() || fp == lcmx_msgs::records_z_t::getHash()) {
      auto r = batch(bytes);
      if (!r) return std::nullopt;
      return std::move(r->records);
    }
    auto b = lcmx::discovery::decode_beacon(bytes);
    if (!b) return std::nullopt;
    std::vector<beacon_t> one{std::move(*b)};
    keep(one);
    return one;
  }

 private:
  void keep(const std::vector<beacon_t>& records) {
    for (const auto& b : records) held_[{b.participant_id, b.revision}] = lcmx::discovery::encode_beacon(b);
  }
  std::map<std::pair<std::int64_t, std::int64_t>, std::vector<std::byte>> held_;
};

// Drains the vehicle group on a thread of its own and hands every discovery datagram to `fn`
// (with whether it holds records: a beacon_t or a batch) until destroyed.
class VehiclePump {
 public:
  using Fn = std::function<void(const lcmx::udpm::Message&, bool record)>;
  // Joined to the group when constructed: it hears everything sent after.
  VehiclePump(const lcmx::udpm::GroupConfig& v, Fn fn)
      : listen_(lcmx::udpm::Group::open(v)), thread_([this, fn = std::move(fn)] {
          while (!stop_) {
            listen_.drain([&](const lcmx::udpm::Message& m) {
              if (m.channel != lcmx::discovery::kBeaconChannel) return;
              const auto fp = lcmx::discovery::fingerprint_of(m.data);
              fn(m, fp == beacon_t::getHash() || fp == lcmx_msgs::records_t::getHash() ||
                        fp == lcmx_msgs::records_z_t::getHash());
            });
            std::this_thread::sleep_for(2ms);  // a test's pump: polls its socket
          }
        }) {}
  ~VehiclePump() { stop(); }
  void stop() {
    stop_ = true;
    if (thread_.joinable()) thread_.join();
  }

 private:
  std::atomic<bool> stop_{false};
  lcmx::udpm::Group listen_;
  std::thread thread_;
};

// A vehicle-scope receiver (participant `id` of host `host`, one topic) that hears the group
// only through a VehiclePump: host messages always, records only once `pass_records` is set.
struct GatedReceiver {
  lcmx::test::TmpDir dir;
  lcmx::udpm::GroupConfig local;
  std::uint64_t host;
  Log log;
  Discovery r;
  std::atomic<bool> pass_records{false};
  VehiclePump pump;
  GatedReceiver(const lcmx::udpm::GroupConfig& v, std::uint64_t h, const lcmx::udpm::GroupConfig& l, std::int64_t id,
                std::string topic, const char* dir_name)
      : dir(dir_name), local(l), host(h),
        r(fed_vehicle_options(v, h, l, dir.path),
          [=] { return beacon_of(id, h, {topic}, beacon_t::SCOPE_VEHICLE); }, log.fn()),
        pump(v, [this](const lcmx::udpm::Message& m, bool record) {
          if (!record || pass_records) r.deliver(m);
        }) {}
  ~GatedReceiver() {
    pump.stop();
    Registry::remove(host, local, dir.path);
  }
};
}  // namespace

TEST_CASE("vehicle scope: a participant that is not its host's speaker ignores the group's discovery - it takes other "
          "hosts from its host's vehicle table alone, goodbyes too",
          "[discovery][vehicle]") {
  const auto v = group_of(57);
  FakeHost a(0xa5, group_of(58), v), b(0xb6, group_of(59), v);
  b.add(61, {"X"});
  REQUIRE(eventually([&] { return b.ps[0].v->speaking(); }));
  // r: another process of host b (its registry), handed every datagram of the vehicle group by
  // this test's pump, as the runtime's front door would if it let them through.
  Log lr;
  Discovery r(fed_vehicle_options(v, b.host, b.local, b.dir.path),
              [] { return beacon_of(62, 0xb6, {"X"}, beacon_t::SCOPE_VEHICLE); }, lr.fn());
  std::atomic<int> handed{0};
  VehiclePump pump(v, [&](const lcmx::udpm::Message& m, bool) {
    ++handed;
    r.deliver(m);
  });
  a.add(51, {"X"});
  a.add(52, {"Y"});
  REQUIRE(eventually([&] { return b.vlog.count(Change::joined, 51) >= 1 && b.vlog.count(Change::joined, 52) >= 1; }));
  REQUIRE(eventually([&] { return lr.count(Change::joined, 51) == 1; }, 3000ms));
  REQUIRE(eventually([&] { return r.complete(); }, 3000ms));
  const auto c = r.counters();
  CHECK(!r.speaking());
  CHECK(!r.listening());
  CHECK(handed.load() > 0);
  CHECK(c.beacons_received == c.table_records);  // every record it took came from the table
  CHECK(c.table_records == 1);
  CHECK(lr.count(Change::joined, 52) == 0);  // Y: not its topic
  CHECK(c.requests_sent == 0);
  CHECK(c.forged == 0);
  CHECK(c.malformed == 0);
  // A participant that leaves host a: the table tells r.
  a.ps.erase(a.ps.begin());  // 51
  REQUIRE(eventually([&] { return lr.count(Change::left, 51) == 1; }, 3000ms));
  CHECK(r.counters().requests_sent == 0);
  pump.stop();
}

TEST_CASE("vehicle scope: a participant whose speaker cannot write the vehicle table listens to the group itself - "
          "and follows the table again once it is written",
          "[discovery][vehicle]") {
  const auto v = group_of(60);
  FakeHost a(0xa7, group_of(61), v), b(0xb8, group_of(62), v);
  // A directory where b's table would be: its speaker cannot write it, nobody can read it.
  std::filesystem::create_directory(table_path(b));
  b.add(71, {"X"});
  REQUIRE(eventually([&] { return b.ps[0].v->speaking(); }));
  Log lr;
  Discovery r(fed_vehicle_options(v, b.host, b.local, b.dir.path),
              [] { return beacon_of(72, 0xb8, {"X"}, beacon_t::SCOPE_VEHICLE); }, lr.fn());
  VehiclePump pump(v, [&](const lcmx::udpm::Message& m, bool) { r.deliver(m); });
  a.add(81, {"X"});
  REQUIRE(eventually([&] { return b.vlog.count(Change::joined, 81) >= 1; }));
  // No table for half the lease: r may act for the host, hears its speaker and stands down, and
  // listens to the group itself (without that it would never hear of 81).
  REQUIRE(eventually([&] { return r.listening() && !r.speaking(); }, 3000ms));
  REQUIRE(eventually([&] { return lr.count(Change::joined, 81) == 1; }, 3000ms));
  CHECK(r.counters().tables_refused >= 1);
  // The table can be written again: r follows it (and no longer listens).
  std::filesystem::remove(table_path(b));
  REQUIRE(eventually([&] { return !r.listening(); }, 3000ms));
  CHECK(!r.speaking());
  CHECK(lr.count(Change::left, 81) == 0);  // the table holds what r heard: nothing left
  a.add(82, {"X"});
  REQUIRE(eventually([&] { return lr.count(Change::joined, 82) == 1; }, 3000ms));
  CHECK(r.counters().table_records >= 1);
  pump.stop();
}

TEST_CASE("vehicle scope: a digest mismatch asks for the index, then for the missing records - repaired", "[discovery][vehicle]") {
  const auto v = group_of(14);
  FakeHost a(0xa3, group_of(15), v);
  a.add(31, {"X"});
  a.add(32, {"Y"});
  // r hears the vehicle group only through what this test hands it: no record at first.
  GatedReceiver g(v, 0xc4, group_of(16), 41, "X", "lcmx_vr");
  // a's records went out when its participants joined, and r missed them: heartbeats disagree.
  std::this_thread::sleep_for(300ms);  // (the first records pass by unseen: the point of the test)
  CHECK(g.log.count(Change::joined, 31) == 0);
  g.pass_records = true;
  REQUIRE(eventually([&] { return g.log.count(Change::joined, 31) == 1 && g.log.count(Change::joined, 32) == 1; },
                     3000ms));
  std::uint64_t answered = 0;
  for (auto& p : a.ps) answered += p.v->counters().requests_answered;
  CHECK(answered >= 1);
}

TEST_CASE("vehicle scope: receivers that miss the same records ask once between them, not once each",
          "[discovery][vehicle]") {
  const auto v = group_of(30);
  FakeHost a(0xa9, group_of(31), v);
  a.add(91, {"X"});
  a.add(92, {"Y"});
  // Six receivers (each its own host) hear the group only through this test's pump: a's
  // records pass them by at first, then all six see a's heartbeats disagree at the same time.
  constexpr int kReceivers = 6;
  lcmx::test::TmpDir rdir("lcmx_vf");
  std::vector<Log> logs(kReceivers);
  std::vector<std::unique_ptr<Discovery>> rs;
  for (int k = 0; k < kReceivers; ++k) {
    const std::uint64_t host = 0xd0 + static_cast<std::uint64_t>(k);
    rs.push_back(std::make_unique<Discovery>(
        fed_vehicle_options(v, host, group_of(32), rdir.path),
        [host, k] { return beacon_of(100 + k, host, {"Z"}, beacon_t::SCOPE_VEHICLE); },
        logs[static_cast<std::size_t>(k)].fn()));
  }
  std::atomic<bool> pass_records{false};
  std::atomic<int> requests_to_a{0};
  VehiclePump pump(v, [&](const lcmx::udpm::Message& m, bool record) {
    if (!record && pass_records) {
      if (auto h = lcmx::discovery::decode_host_beacon(m.data); h && h->kind == host_beacon_t::KIND_REQUEST &&
                                                                 h->target_host == 0xa9)
        ++requests_to_a;
    }
    if (!record || pass_records)
      for (auto& r : rs) r->deliver(m);
  });
  std::this_thread::sleep_for(300ms);  // (a's first records pass by unseen: the point of the test)
  for (auto& l : logs) CHECK(l.count(Change::joined, 91) == 0);
  pass_records = true;
  const bool repaired = eventually([&] {
    return std::all_of(logs.begin(), logs.end(),
                       [](Log& l) { return l.count(Change::joined, 91) == 1 && l.count(Change::joined, 92) == 1; });
  }, 3000ms);
  pump.stop();
  std::uint64_t folded = 0;
  for (auto& r : rs) folded += r->counters().requests_folded;
  INFO("requests to a: " << requests_to_a.load() << ", folded: " << folded);
  REQUIRE(repaired);
  // Each asking for itself: an index request and a record request each (12). Folded: the first
  // request's answer, multicast, serves the rest.
  CHECK(requests_to_a.load() <= kReceivers);
  CHECK(folded >= 1);
  rs.clear();
  Registry::remove(0xd0, group_of(32), rdir.path);
  for (int k = 1; k < kReceivers; ++k) Registry::remove(0xd0 + static_cast<std::uint64_t>(k), group_of(32), rdir.path);
}

TEST_CASE("vehicle scope: a burst of records goes out in batches - one datagram for many, a large record alone",
          "[discovery][vehicle]") {
  const auto v = group_of(35);
  FakeHost a(0xaa, group_of(36), v), b(0xbb, group_of(37), v);
  b.add(200, {"Q"});  // an audience on another host
  // Counts host a's discovery datagrams that hold records, and the records in them.
  std::mutex mu;
  int datagrams = 0, records = 0, alone = 0, compressed = 0, with_heartbeat = 0;
  std::size_t largest_batch = 0;
  HeardRecords heard;  // (the pump's thread only)
  VehiclePump pump(v, [&](const lcmx::udpm::Message& m, bool record) {
    if (!record) return;
    const bool batch = lcmx::discovery::fingerprint_of(m.data) != beacon_t::getHash();
    std::optional<lcmx_msgs::records_t> decoded;
    std::optional<std::vector<beacon_t>> rs;
    if (batch && (decoded = heard.batch(m.data))) rs = decoded->records;
    if (!batch) rs = heard.any(m.data);
    if (!rs || rs->empty() || rs->front().host_id != 0xaa) return;
    std::lock_guard lock(mu);
    ++datagrams;
    if (lcmx::discovery::fingerprint_of(m.data) == lcmx_msgs::records_z_t::getHash()) ++compressed;
    if (decoded && !decoded->state.empty()) ++with_heartbeat;
    records += static_cast<int>(rs->size());
    if (rs->size() == 1) ++alone;
    else largest_batch = std::max(largest_batch, m.data.size());
  });
  // Twelve participants start at once, one of them with a record larger than a batch.
  for (int k = 0; k < 12; ++k)
    a.add(210 + k, {"T" + std::to_string(k)}, [k](beacon_t& bc) {
      if (k == 5) bc.process_name = std::string(lcmx::discovery::kBatchBytes + 100, 'p');
    });
  REQUIRE(eventually([&] {
    for (int k = 0; k < 12; ++k)
      if (b.vlog.count(Change::joined, 210 + k) != 1) return false;
    return true;
  }, 5000ms));
  // The pump polls its socket: it may be a few milliseconds behind b.
  CHECK(eventually([&] {
    std::lock_guard lock(mu);
    return records >= 12;
  }, 3000ms));
  pump.stop();
  std::lock_guard lock(mu);
  INFO("datagrams " << datagrams << ", records " << records << ", alone " << alone << ", largest batch "
                    << largest_batch << ", compressed " << compressed << ", with a heartbeat " << with_heartbeat);
  // One per record without batches; with them, the burst's records share datagrams.
  CHECK(2 * datagrams <= records);
  CHECK(alone >= 1);  // the large one
  CHECK(largest_batch <= lcmx::discovery::kBatchBytes);
  CHECK(compressed >= 1);  // records of one host alike: the batches went deflated
  CHECK(with_heartbeat >= 1);  // a pass's last batch ends with the speaker's heartbeat
  CHECK(b.ps[0].v->counters().malformed == 0);
  CHECK(b.ps[0].v->counters().forged == 0);
}

TEST_CASE("vehicle scope: complete once it holds what every host's digest names - not while records are missing",
          "[discovery][vehicle]") {
  const auto v = group_of(38);
  FakeHost a(0xac, group_of(39), v);
  a.add(301, {"X"});
  a.add(302, {"Y"});
  // r hears a's heartbeats and index, not its records: it knows a holds two it lacks.
  GatedReceiver g(v, 0xcd, group_of(40), 311, "Z", "lcmx_vc");
  CHECK_FALSE(g.r.complete());
  std::this_thread::sleep_for(400ms);  // 8 periods (complete could latch after 1.5): it must not
  CHECK_FALSE(g.r.complete());
  g.pass_records = true;
  REQUIRE(eventually([&] { return g.r.complete(); }, 3000ms));
  // Latched only after on_change was told of every record the digest names.
  CHECK(g.log.count(Change::joined, 301) == 1);
  CHECK(g.log.count(Change::joined, 302) == 1);
}

TEST_CASE("vehicle scope: alone on its group, complete after a period and a half", "[discovery][vehicle]") {
  const auto v = group_of(41);
  lcmx::test::TmpDir rdir("lcmx_va");
  auto o = fed_vehicle_options(v, 0xce, group_of(42), rdir.path);
  o.period = 200ms;
  o.lease = 2000ms;
  const auto start = Clock::now();
  Discovery r(o, [] { return beacon_of(321, 0xce, {"Z"}, beacon_t::SCOPE_VEHICLE); }, nullptr);
  CHECK_FALSE(r.complete());
  REQUIRE(eventually([&] { return r.complete(); }, 3000ms));
  CHECK(Clock::now() - start >= 300ms);  // no sooner: a host's heartbeat may still be on its way
  Registry::remove(0xce, group_of(42), rdir.path);
}

TEST_CASE("trust: goodbyes, newer records and source claims only from the host's own address", "[discovery][hostile]") {
  auto o = fed_observer_options(group_of(17));
  Log lr;
  Discovery r(o, nullptr, lr.fn());
  const char* real = "10.9.0.1";
  const char* evil = "10.9.0.66";
  auto rec = [](std::int64_t id, std::int64_t host, std::int64_t rev) {
    auto b = beacon_of(id, static_cast<std::uint64_t>(host), {"T"}, beacon_t::SCOPE_VEHICLE);
    b.version = lcmx::discovery::kBeaconVersion;
    b.revision = rev;
    b.vehicle_source = "10.9.0.1:7668";
    return b;
  };
  r.deliver(message_of(lcmx::discovery::encode_host_beacon(heartbeat_of(77, {{5, 1}})), real));  // binds host 77
  r.deliver(message_of(lcmx::discovery::encode_beacon(rec(5, 77, 1)), real));
  REQUIRE(lr.count(Change::joined, 5) == 1);
  // A goodbye naming it from elsewhere.
  auto bye = rec(5, 77, 1);
  bye.flags = beacon_t::FLAG_GOODBYE;
  r.deliver(message_of(lcmx::discovery::encode_beacon(bye), evil));
  // A "newer" record of it (the old sequence = INT64_MAX attack) from elsewhere.
  r.deliver(message_of(lcmx::discovery::encode_beacon(rec(5, 77, INT64_MAX)), evil));
  // The same participant id claimed by another host.
  r.deliver(message_of(lcmx::discovery::encode_beacon(rec(5, 78, 9)), evil));
  // A source claim that is not the sender's address.
  auto claim = rec(6, 77, 1);
  claim.vehicle_source = "10.9.0.200:7668";
  r.deliver(message_of(lcmx::discovery::encode_beacon(claim), real));
  CHECK(r.counters().forged == 4);
  // The same in a batch (records_t): each record is judged as if it came alone.
  const std::vector<std::vector<std::byte>> batch = {lcmx::discovery::encode_beacon(bye),
                                                     lcmx::discovery::encode_beacon(rec(7, 77, 1))};
  r.deliver(message_of(lcmx::discovery::encode_records(77, batch), evil));
  CHECK(r.counters().forged == 6);
  // And compressed (records_z_t): inflated, then the same rules.
  const std::vector<std::vector<std::byte>> alike = {lcmx::discovery::encode_beacon(bye), lcmx::discovery::encode_beacon(rec(7, 77, 1)),
                                                     lcmx::discovery::encode_beacon(rec(8, 77, 1)), lcmx::discovery::encode_beacon(rec(9, 77, 1))};
  const auto deflated = lcmx::discovery::encode_batch(77, alike);
  REQUIRE(lcmx::discovery::fingerprint_of(deflated) == lcmx_msgs::records_z_t::getHash());
  r.deliver(message_of(deflated, evil));
  CHECK(r.counters().forged == 10);
  CHECK(lr.count(Change::left, 5) == 0);
  CHECK(lr.count(Change::joined, 6) == 0);
  CHECK(lr.count(Change::joined, 7) == 0);
  CHECK(lr.count(Change::joined, 8) == 0);
  auto ps = r.participants();
  REQUIRE(ps.size() == 1);
  CHECK(ps[0].beacon.revision == 1);
  r.deliver(message_of(lcmx::discovery::encode_beacon(bye), real));  // the real one
  CHECK(lr.count(Change::left, 5) == 1);
}

TEST_CASE("vehicle scope: a batch whose closing heartbeat disagrees with what it holds asks for the index at once - one that agrees asks nothing",
          "[discovery][vehicle]") {
  auto o = fed_observer_options(group_of(43));
  Log lr;
  Discovery r(o, nullptr, lr.fn());
  std::atomic<int> asked{0};  // requests for host 77's index heard on the group
  VehiclePump pump(o.group, [&](const lcmx::udpm::Message& m, bool) {
    auto h = lcmx::discovery::decode_host_beacon(m.data);
    if (h && h->kind == host_beacon_t::KIND_REQUEST && h->target_host == 77 && h->wanted.empty()) ++asked;
  });
  const char* speaker = "10.9.0.1";
  auto rec = [](std::int64_t id) { return lcmx::discovery::encode_beacon(remote_record(id, 77, "T")); };
  auto batch = [&](std::vector<std::vector<std::byte>> records, std::map<std::int64_t, std::int64_t> set) {
    return lcmx::discovery::encode_batch(77, records, lcmx::discovery::encode_host_beacon(heartbeat_of(77, std::move(set))));
  };
  // Records 5 and 6, and a heartbeat that names exactly them: nothing to ask.
  r.deliver(message_of(batch({rec(5), rec(6)}, {{5, 1}, {6, 1}}), speaker));
  REQUIRE(lr.count(Change::joined, 6) == 1);
  std::this_thread::sleep_for(300ms);  // several request jitters: the absence of a request is what is checked
  CHECK(asked.load() == 0);
  // Record 7, and a heartbeat that also names 8, which never came: the index is asked for at
  // once, without a second heartbeat (none is sent here).
  r.deliver(message_of(batch({rec(7)}, {{5, 1}, {6, 1}, {7, 1}, {8, 1}}), speaker));
  CHECK(lr.count(Change::joined, 7) == 1);
  CHECK(eventually([&] { return asked.load() >= 1; }, 2000ms));
  pump.stop();
}

TEST_CASE("vehicle scope: a batch compressed against a record held is taken - one against a record not held asks at once",
          "[discovery][vehicle]") {
  auto o = fed_observer_options(group_of(51));
  Log lr;
  Discovery r(o, nullptr, lr.fn());
  std::atomic<int> asked{0};  // requests to host 77 heard on the group (its index or all its records)
  VehiclePump pump(o.group, [&](const lcmx::udpm::Message& m, bool) {
    auto h = lcmx::discovery::decode_host_beacon(m.data);
    if (h && h->kind == host_beacon_t::KIND_REQUEST && h->target_host == 77) ++asked;
  });
  const char* speaker = "10.9.0.1";
  using Records = std::vector<std::vector<std::byte>>;
  auto rec = [](std::int64_t id) { return lcmx::discovery::encode_beacon(remote_record(id, 77, "T")); };
  auto heartbeat = [](std::map<std::int64_t, std::int64_t> set) {
    return lcmx::discovery::encode_host_beacon(heartbeat_of(77, std::move(set)));
  };
  // Record 5, and a heartbeat that names it.
  r.deliver(message_of(lcmx::discovery::encode_batch(77, Records{rec(5)}, heartbeat({{5, 1}})), speaker));
  REQUIRE(lr.count(Change::joined, 5) == 1);
  // Record 6 against record 5 as it was sent: taken.
  const auto five = rec(5);
  const lcmx::discovery::BatchBase held{5, 1, five};
  const auto against_held = lcmx::discovery::encode_batch(77, Records{rec(6)}, heartbeat({{5, 1}, {6, 1}}), &held);
  REQUIRE(lcmx::discovery::batch_base(against_held).first == 5);
  r.deliver(message_of(against_held, speaker));
  CHECK(lr.count(Change::joined, 6) == 1);
  CHECK(r.counters().missed_batches == 0);
  CHECK(r.counters().malformed == 0);
  // Record 7 against record 9, which never came here: lost to r, which asks host 77 at once
  // (no second heartbeat is sent here).
  const auto nine = rec(9);
  const lcmx::discovery::BatchBase missing{9, 1, nine};
  r.deliver(message_of(
      lcmx::discovery::encode_batch(77, Records{rec(7)}, heartbeat({{5, 1}, {6, 1}, {7, 1}, {9, 1}}), &missing), speaker));
  CHECK(lr.count(Change::joined, 7) == 0);
  CHECK(r.counters().missed_batches == 1);
  CHECK(r.counters().malformed == 0);
  CHECK(eventually([&] { return asked.load() >= 1; }, 2000ms));
  pump.stop();
}

TEST_CASE("vehicle scope: an observer that holds a full record inflates a batch against its vehicle view",
          "[discovery][vehicle][observer]") {
  auto o = fed_observer_options(group_of(53));
  Log lr;
  Discovery r(o, nullptr, lr.fn());
  const char* speaker = "10.9.0.1";
  using Records = std::vector<std::vector<std::byte>>;
  // Record 5 as an observer's query gets it: a local (shm) match and statistics.
  auto full = remote_record(5, 77, "T");
  full.endpoints[0].messages = 1234;
  lcmx_msgs::match_t local{};
  local.publisher_participant = 4;
  local.publisher_endpoint = 1;
  local.path = "shm";
  local.received = 99;
  full.endpoints[0].matches.push_back(local);
  full.endpoints[0].num_matches = 1;
  full.sequence = 17;
  full.timestamp_us = 1700000000000000;
  r.deliver(message_of(lcmx::discovery::encode_beacon(full), speaker));
  REQUIRE(lr.count(Change::joined, 5) == 1);
  // What other hosts are sent of it (the speaker's base): no local match, no statistics.
  auto view = full;
  view.endpoints[0].messages = 0;
  view.endpoints[0].matches.clear();
  view.endpoints[0].num_matches = 0;
  view.sequence = 0;
  view.timestamp_us = 0;
  const auto view_bytes = lcmx::discovery::encode_beacon(view);
  const lcmx::discovery::BatchBase base{5, 1, view_bytes};
  const auto batch = lcmx::discovery::encode_batch(
      77, Records{lcmx::discovery::encode_beacon(remote_record(6, 77, "T"))},
      lcmx::discovery::encode_host_beacon(heartbeat_of(77, {{5, 1}, {6, 1}})), &base);
  REQUIRE(lcmx::discovery::batch_base(batch).first == 5);
  r.deliver(message_of(batch, speaker));
  CHECK(lr.count(Change::joined, 6) == 1);
  CHECK(r.counters().missed_batches == 0);
}

TEST_CASE("vehicle scope: a receiver that holds none of a host's records asks for all of them at once - one that holds "
          "some asks for the index",
          "[discovery][vehicle]") {
  auto o = fed_observer_options(group_of(52));
  Log lr;
  Discovery r(o, nullptr, lr.fn());
  std::atomic<int> views{0}, index{0};  // requests to host 77 heard on the group
  VehiclePump pump(o.group, [&](const lcmx::udpm::Message& m, bool) {
    auto h = lcmx::discovery::decode_host_beacon(m.data);
    if (!h || h->kind != host_beacon_t::KIND_REQUEST || h->target_host != 77) return;
    if (h->wanted.empty()) ++index;
    if (h->wanted.size() == 1 && h->wanted[0] == host_beacon_t::WANT_VIEWS) ++views;
  });
  const char* speaker = "10.9.0.1";
  auto beat = [&](std::map<std::int64_t, std::int64_t> set) {
    r.deliver(message_of(lcmx::discovery::encode_host_beacon(heartbeat_of(77, std::move(set))), speaker));
  };
  // Two heartbeats that name a record r does not hold, and r holds none of 77's.
  beat({{5, 1}});
  beat({{5, 1}});
  REQUIRE(eventually([&] { return views.load() >= 1; }, 2000ms));
  CHECK(index.load() == 0);
  // It holds 5 now; 77's set grows by 6: the index, as before.
  r.deliver(message_of(lcmx::discovery::encode_beacon(remote_record(5, 77, "T")), speaker));
  REQUIRE(lr.count(Change::joined, 5) == 1);
  const auto views_before = views.load();
  REQUIRE(eventually([&] {  // (its requests are rate-limited to one per period: heartbeats until it asks)
    beat({{5, 1}, {6, 1}});
    return index.load() >= 1;
  }, 3000ms));
  CHECK(views.load() == views_before);
  pump.stop();
}

TEST_CASE("trust: another host's record naming this process or a participant of this host is refused", "[discovery][hostile]") {
  const auto v = group_of(25);
  FakeHost a(0xc6, group_of(26), v);
  lcmx::discovery::Options o;
  o.group = v;
  o.scope = beacon_t::SCOPE_VEHICLE;
  o.period = 50ms;
  o.lease = 500ms;
  o.shared_group = std::make_shared<lcmx::udpm::Group>(lcmx::udpm::Group::open(v));
  o.registry = Registry::open({.host_id = 0xc6, .group = group_of(26), .directory = a.dir.path});
  Log lr;
  Discovery r(o, [] { return beacon_of(62, 0xc6, {"X"}, beacon_t::SCOPE_VEHICLE); }, lr.fn());  // this process
  REQUIRE(eventually([&] { return r.speaking(); }));  // (it hears the group: its host's speaker)
  a.add(61, {"X"});  // another participant of this host (its own registry object, as another process)
  auto in_registry = [&](std::int64_t id) {
    auto& ri = r.registry()->impl();
    for (std::uint32_t i = 0; i < ri.slot_count; ++i)
      if (lcmx::discovery::reg::state_of(ri.slot(i).state.load()) == lcmx::discovery::reg::kLive &&
          ri.slot(i).participant_id.load() == id)
        return true;
    return false;
  };
  REQUIRE(eventually([&] { return in_registry(61) && in_registry(62); }));
  // Host 78 (bound to its address by its heartbeat) claims 61 and 62, and announces 63.
  const char* ip = "10.9.0.1";
  auto rec = [](std::int64_t id) { return remote_record(id, 78, "X"); };
  r.deliver(message_of(lcmx::discovery::encode_host_beacon(heartbeat_of(78, {{61, 1}, {62, 1}, {63, 1}})), ip));
  r.deliver(message_of(lcmx::discovery::encode_beacon(rec(61)), ip));
  r.deliver(message_of(lcmx::discovery::encode_beacon(rec(62)), ip));
  r.deliver(message_of(lcmx::discovery::encode_beacon(rec(63)), ip));
  CHECK(r.counters().forged == 2);
  CHECK(lr.count(Change::joined, 61) == 0);
  CHECK(lr.count(Change::joined, 62) == 0);
  CHECK(lr.count(Change::joined, 63) == 1);  // the host's own participant is taken
  const auto ps = r.participants();
  REQUIRE(ps.size() == 1);
  CHECK(ps[0].beacon.participant_id == 63);
}

TEST_CASE("a full table never expires a known peer - its host's heartbeat keeps it", "[discovery][hostile]") {
  auto o = fed_observer_options(group_of(18));
  o.max_participants = 2;
  Discovery r(o, nullptr, nullptr);
  const char* ip = "10.9.0.1";
  auto rec = [](std::int64_t id) {
    auto b = beacon_of(id, 77, {"T"}, beacon_t::SCOPE_VEHICLE);
    b.version = lcmx::discovery::kBeaconVersion;
    b.revision = 1;
    return b;
  };
  r.deliver(message_of(lcmx::discovery::encode_host_beacon(heartbeat_of(77, {{5, 1}, {6, 1}})), ip));
  r.deliver(message_of(lcmx::discovery::encode_beacon(rec(5)), ip));
  r.deliver(message_of(lcmx::discovery::encode_beacon(rec(6)), ip));
  for (int k = 100; k < 200; ++k) r.deliver(message_of(lcmx::discovery::encode_beacon(rec(k)), ip));
  CHECK(r.counters().refused == 100);
  // Past the host's lease (300 ms), its heartbeats keep coming: 5 and 6 stay; more refusals too.
  const auto end = Clock::now() + 1000ms;
  while (Clock::now() < end) {
    r.deliver(message_of(lcmx::discovery::encode_host_beacon(heartbeat_of(77, {{5, 1}, {6, 1}})), ip));
    r.deliver(message_of(lcmx::discovery::encode_beacon(rec(300)), ip));
    std::this_thread::sleep_for(50ms);  // the host's period
  }
  CHECK(r.participants().size() == 2);
  CHECK(r.counters().leases_expired == 0);
}

TEST_CASE("a flood of queries is answered at most once per period", "[discovery][hostile]") {
  const auto v = group_of(19);
  FakeHost a(0xa5, group_of(20), v);
  a.add(51, {"X"});
  REQUIRE(eventually([&] { return a.ps[0].v->speaking(); }));
  auto g = lcmx::udpm::Group::open(v);
  host_beacon_t q{};
  q.version = lcmx::discovery::kHostBeaconVersion;
  q.kind = host_beacon_t::KIND_REQUEST;
  q.scope = beacon_t::SCOPE_VEHICLE;
  q.host_id = 0xeeee;
  q.wanted = {host_beacon_t::WANT_ALL};
  q.num_wanted = 1;
  const auto bytes = lcmx::discovery::encode_host_beacon(q);
  const auto sent0 = a.ps[0].v->counters().beacons_sent;
  const auto t0 = Clock::now();
  for (int k = 0; k < 200; ++k) g.publish(lcmx::discovery::kBeaconChannel, bytes);
  REQUIRE(eventually([&] { return a.ps[0].v->counters().requests_limited >= 100; }, 3000ms));
  std::this_thread::sleep_for(200ms);  // the answers the flood got, if any more came
  const auto elapsed = std::chrono::duration_cast<std::chrono::milliseconds>(Clock::now() - t0);
  const auto sent = a.ps[0].v->counters().beacons_sent - sent0;
  // Per period (50 ms): a heartbeat, at most one answer (its record and the index).
  CHECK(sent <= static_cast<std::uint64_t>(4 * (elapsed / 50ms + 2)));
}

TEST_CASE("N = 200 processes on one host: everyone is known, deaths seen within 100 ms, all clean at the end", "[discovery][stress]") {
  const auto g = group_of(21);
  RegistryCleanup clean{g};
  const auto url = url_of(g);
  constexpr int N = 200;
  std::vector<lcmx::test::Child> peers;
  std::vector<std::int64_t> ids;
  const auto t0 = Clock::now();
  for (int k = 0; k < N; ++k)
    peers.push_back(lcmx::test::spawn({LCMX_DISCOVERY_PEER, "--group", url, "--topics",
                                       "S" + std::to_string(k) + ",S" + std::to_string((k + 1) % N), "--period", "400",
                                       "--lease", "1500"}));
  for (auto& p : peers) ids.push_back(ready_id(p));
  INFO("started in " << std::chrono::duration_cast<std::chrono::milliseconds>(Clock::now() - t0).count() << " ms");
  auto o = options_of(g);
  o.period = 400ms;
  o.lease = 1500ms;
  Log la;
  std::vector<std::string> mine;
  for (int k = 0; k < 10; ++k) mine.push_back("S" + std::to_string(k));
  Discovery a(o, [&] { return beacon_of(1, lcmx::discovery::host_id(), mine); }, la.fn());
  auto ob = o;
  ob.observer = true;
  Discovery observer(ob, nullptr, nullptr);
  REQUIRE(eventually([&] { return observer.participants().size() == N + 1; }, 20000ms));
  // a is told of the participants its topics concern (0..9 and 199) and few others (filter).
  REQUIRE(eventually([&] { return a.participants().size() >= 11; }, 5000ms));
  CHECK(a.participants().size() <= 30);
  // Deaths: seen by a within 100 ms of the kill.
  for (int k = 1; k <= 5; ++k) {
    INFO("victim " << k << (a.registry()->impl().header->speaker.load() == ids[static_cast<std::size_t>(k)] ? " (the speaker)" : ""));
    const auto tk = Clock::now();
    peers[static_cast<std::size_t>(k)].kill(SIGKILL);
    auto* reg = &a.registry()->impl();
    std::int64_t slot = -1;
    for (std::uint32_t i = 0; i < reg->slot_count; ++i)
      if (reg->slot(i).participant_id.load() == ids[static_cast<std::size_t>(k)]) slot = i;
    eventually([&] { return lcmx::discovery::reg::state_of(reg->slot(static_cast<std::uint32_t>(slot)).state.load()) != lcmx::discovery::reg::kLive; }, 3000ms);
    INFO("slot freed after " << std::chrono::duration_cast<std::chrono::milliseconds>(Clock::now() - tk).count() << " ms");
    REQUIRE(eventually([&] { return la.count(Change::left, ids[static_cast<std::size_t>(k)]) == 1; }, 3000ms));
    CHECK(*la.when(Change::left, ids[static_cast<std::size_t>(k)]) - tk < 100ms);
  }
  REQUIRE(eventually([&] { return observer.participants().size() == N + 1 - 5; }, 3000ms));
  CHECK(a.counters().leases_expired == 0);
  CHECK(observer.counters().leases_expired == 0);  // no false expiry through the launch
  // Clean exits: everyone leaves, the registry empties.
  for (auto& p : peers) p.kill(SIGTERM);
  REQUIRE(eventually([&] { return observer.participants().size() == 1; }, 20000ms));  // a
  for (auto& p : peers) p.wait(5000ms);
  CHECK(a.registry()->occupied() == 1);
}

TEST_CASE("4 emulated hosts x 10 processes: every host sees the others' participants, a death and a lost host", "[discovery][multihost]") {
  std::string why;
  if (!lcmx::test::netns_available(&why)) {
    WARN("skipped: " << why);
    return;
  }
  constexpr int H = 4, P = 10;
  auto emu = lcmx::test::Emulation::create({.hosts = H});
  const auto local = group_of(22), vehicle = group_of(23);
  struct Cleanup {
    lcmx::udpm::GroupConfig g;
    ~Cleanup() {
      for (int h = 0; h < H; ++h) Registry::remove(0xe0 + static_cast<std::uint64_t>(h), g);
    }
  } clean{local};
  const auto lurl = url_of(local);
  const std::string vurl = "udpm://" + vehicle.address + ":" + std::to_string(vehicle.port) + "?ttl=1&iface=eth";
  std::vector<std::vector<lcmx::test::Child>> peers(H);
  std::vector<std::vector<std::int64_t>> ids(H);
  for (int h = 0; h < H; ++h)
    for (int k = 0; k < P; ++k) {
      peers[h].push_back(emu.spawn(h, {LCMX_DISCOVERY_PEER, "--group", lurl, "--vehicle", vurl, "--host-id",
                                       std::to_string(0xe0 + h), "--topics", "H" + std::to_string(h) + "_" + std::to_string(k),
                                       "--period", "200", "--lease", "1000", "--watch"}));
      ids[h].push_back(ready_id(peers[h].back()));
    }
  // Host 1's first participant watches the vehicle scope: it must see 30 remote participants.
  auto& w = peers[1][0];
  std::set<std::int64_t> vjoined, vleft;
  auto read = [&](std::chrono::milliseconds t) {
    if (auto line = w.read_line(t)) {
      if (line->rfind("VJOINED ", 0) == 0) vjoined.insert(std::stoll(line->substr(8)));
      if (line->rfind("VLEFT ", 0) == 0) vleft.insert(std::stoll(line->substr(6)));
    }
  };
  const auto t0 = Clock::now();
  while (vjoined.size() < (H - 1) * P && Clock::now() - t0 < 10s) read(100ms);
  REQUIRE(vjoined.size() == (H - 1) * P);
  // A participant of host 0 killed -9: gone at host 1 within the lease (its speaker says goodbye).
  const auto victim = ids[0][5];
  auto tk = Clock::now();
  peers[0][5].kill(SIGKILL);
  while (!vleft.count(victim) && Clock::now() - tk < 5s) read(50ms);
  REQUIRE(vleft.count(victim));
  CHECK(Clock::now() - tk < 1000ms);
  // Host 2 lost (every process killed): its participants gone at host 1 after the host's lease.
  tk = Clock::now();
  for (auto& p : peers[2]) p.kill(SIGKILL);
  auto all_gone = [&] {
    for (auto id : ids[2])
      if (!vleft.count(id)) return false;
    return true;
  };
  while (!all_gone() && Clock::now() - tk < 5s) read(50ms);
  REQUIRE(all_gone());
  CHECK(Clock::now() - tk < 2000ms);
}
