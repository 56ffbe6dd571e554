// Discovery (discovery.hpp, docs/discovery.md): the registry reader, the speaker and the
// per-host tables of the speaker protocol.
#include "lcmx/discovery/discovery.hpp"

#include <arpa/inet.h>
#include <poll.h>
#include <sys/eventfd.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <cstdint>
#include <map>
#include <mutex>
#include <set>
#include <thread>
#include <vector>

#include <spdlog/spdlog.h>

#include "lcmx/discovery/beacon_codec.hpp"
#include "lcmx/discovery/identity.hpp"
#include "lcmx/lcmtypes/envelope.hpp"
#include "lcmx/shm/futex.hpp"
#include "registry_impl.hpp"
#include "vehicle_table.hpp"

namespace lcmx::discovery {

using Clock = std::chrono::steady_clock;
using lcmx_msgs::beacon_t;
using lcmx_msgs::host_beacon_t;

// Remote host expiry reads what is queued first; a check made this long after that read began
// (this process was stopped, or starved of a CPU, in between) reads again, at most kMaxReads times.
constexpr auto kStall = std::chrono::milliseconds(100);
constexpr int kMaxReads = 3;
// Registry passes: on average at most one per kCoalesce (a 500-process launch changes the
// registry thousands of times a second; every reader folds them into few passes), in bursts of
// up to kPassBurst: a new participant changes its slot up to three times in a few milliseconds
// (it joins, writes its first state, then its first endpoints), and the last change must not
// wait a whole kCoalesce — a publisher's ring holds what it publishes meanwhile only for so
// long (the start-up race). Only passes made for a change count (not the full pass of every
// period, nor a retry of a slot read half-written: those come once per kCoalesce).
constexpr auto kCoalesce = std::chrono::milliseconds(20);
constexpr std::size_t kPassBurst = 4;
// The speaker polls its participants' pidfds at least this often (death notice).
constexpr auto kSpeakerTick = std::chrono::milliseconds(20);
// The speaker sends the records of changed participants this long after the first change.
constexpr auto kRecordDelay = std::chrono::milliseconds(30);
// A claimed slot whose claimer is gone is freed after this long.
constexpr std::int64_t kClaimTimeoutNs = 2'000'000'000;
// A receiver's request (for a host's index or records) waits a random time up to this long,
// then goes only for what no one asked meanwhile: every process of a host hears the same
// heartbeat and the same index at the same moment, and one multicast answer serves them all
// (issue 33: 8 hosts x 50 processes sent 3.4 MB of requests before any host matched).
constexpr auto kRequestJitter = std::chrono::milliseconds(40);
// A vehicle-scope Discovery is complete (Discovery::complete) no sooner than this many periods
// after it started: every live host's heartbeat came by then, with one late by half a period.
constexpr double kCompleteAfter = 1.5;

#ifndef SYS_pidfd_open
#define SYS_pidfd_open 434
#endif

namespace {

std::uint32_t ip_of(const std::string& source) {  // "a.b.c.d:port" -> network-order address, 0 if none
  const auto colon = source.rfind(':');
  if (colon == std::string::npos) return 0;
  std::uint32_t parts[4];
  if (std::sscanf(source.substr(0, colon).c_str(), "%u.%u.%u.%u", &parts[0], &parts[1], &parts[2], &parts[3]) != 4)
    return 0;
  std::uint32_t a = 0;
  for (auto p : parts) a = (a << 8) | (p & 0xff);
  return htonl(a);
}

// A record's host id, read before decoding: the int64 at offset 20 of a beacon_t (after its
// fingerprint, version and participant id), 12 of a records_t or a records_z_t (fingerprint,
// version). 0 if the bytes are too short.
constexpr std::size_t kBeaconHostAt = 20, kRecordsHostAt = 12;
std::uint64_t host_at(std::span<const std::byte> bytes, std::size_t offset) {
  lcmtypes::Reader r(bytes);
  r.bytes(offset);
  const auto v = r.i64();
  return r.ok() ? static_cast<std::uint64_t>(v) : 0;
}

// Hash of a beacon without what changes every period (statistics, sequence, time): a change of
// it is structural (endpoints, matches, nodes, flags, sources).
std::uint64_t structural_hash(beacon_t b) {
  b.sequence = 0;
  b.timestamp_us = 0;
  b.revision = 0;
  for (auto& e : b.endpoints) {
    e.messages = 0;
    e.drops = 0;
    e.rate_hz = 0;
    for (auto& m : e.matches) m.received = 0, m.drops = 0;
  }
  const auto bytes = encode_beacon(b);
  return reg::fnv1a(bytes);
}

// What other hosts use of a participant's vehicle record (issue 33): the record without its
// subscribers' local matches (shm, intra-process, and foreign ones: they name publishers of its
// own host) and without statistics (counts, rates, drops, sequence, time). A remote publisher
// looks only for matches naming itself (udp) and for a bridge match (core's
// Matching::count_remote_locked); tools read local matches and statistics from the records
// sent in answer to their query (KIND_WANT_ALL), which are re-read and sent in full. The speaker
// sends this view, and sends a record again only when its structural hash (Spoken::shape)
// changes. nullopt if the bytes do not decode.
std::optional<beacon_t> vehicle_view(std::span<const std::byte> section) {
  auto b = decode_beacon(section);
  if (!b) return std::nullopt;
  b->sequence = 0;
  b->timestamp_us = 0;
  for (auto& e : b->endpoints) {
    std::erase_if(e.matches, [](const lcmx_msgs::match_t& m) {
      return m.publisher_participant == 0 || (m.path != "udp" && m.path != "bridge");
    });
    e.num_matches = static_cast<std::int32_t>(e.matches.size());
    e.messages = 0;
    e.drops = 0;
    e.rate_hz = 0;
    for (auto& m : e.matches) m.received = 0, m.drops = 0;
  }
  return b;
}

// Writes `revision` into an encoded beacon_t's revision field (after the fixed header and the
// process name). Records carry the registry's revision, so a receiver's (id, revision) set and
// its digest agree with the speaker's. False if the bytes are too short.
bool patch_revision(std::vector<std::byte>& bytes, std::int64_t revision) {
  // fingerprint 8, version 4, participant_id 8, host_id 8, pid 4, start_time 8, pid_namespace 8
  constexpr std::size_t kName = 48;
  if (bytes.size() < kName + 4) return false;
  std::uint32_t len = 0;
  for (int k = 0; k < 4; ++k) len = (len << 8) | std::to_integer<std::uint8_t>(bytes[kName + static_cast<std::size_t>(k)]);
  const std::size_t at = kName + 4 + std::size_t{len} + 8;  // after the name and `sequence`
  if (len > bytes.size() || at + 8 > bytes.size()) return false;
  for (int k = 0; k < 8; ++k)
    bytes[at + static_cast<std::size_t>(k)] = static_cast<std::byte>(static_cast<std::uint64_t>(revision) >> (56 - 8 * k));
  return true;
}

std::uint64_t stats_hash(const beacon_t& b) {
  std::uint64_t h = 1469598103934665603ull;
  auto mix = [&](const auto& v) { h = reg::fnv1a(std::as_bytes(std::span(&v, 1)), h); };
  for (const auto& e : b.endpoints) {
    mix(e.messages), mix(e.drops), mix(e.rate_hz);
    for (const auto& m : e.matches) mix(m.received), mix(m.drops);
  }
  return h;
}

std::uint64_t digest_of(const std::map<std::int64_t, std::int64_t>& set) {
  std::uint64_t h = 1469598103934665603ull;
  for (const auto& [id, rev] : set) {
    std::int64_t v[2] = {id, rev};
    h = reg::fnv1a(std::as_bytes(std::span(v)), h);
  }
  return h;
}

}  // namespace

struct Discovery::Impl {
  Options options;
  LocalFn local;
  ChangeFn on_change;
  std::shared_ptr<udpm::Group> group;
  bool receive = true;  // false with a shared group: the owner calls deliver()
  std::shared_ptr<Registry> registry;  // null: a vehicle-scope observer
  Registry::Impl* reg = nullptr;
  bool host_scope = true;
  bool joined_registry = false;
  std::uint64_t own_host = 0;
  std::uint64_t group_hash = 0;
  int wake_fd = -1;                        // eventfd: announce_now()/query()/stop()
  std::atomic<std::uint32_t> wake_word{0};  // private futex: the same, for a non-speaker's wait
  std::atomic<bool> want_announce{true};
  std::atomic<bool> want_query{false};
  std::atomic<bool> stopping{false};
  std::thread thread, rx_thread;
  std::int64_t sequence = 0;
  std::int64_t udp_sent = 0;  // discovery thread only
  std::atomic<std::int64_t> self_id{0};
  std::atomic<bool> is_speaker{false};
  // Discovery::complete(): latched by update_complete (under mutex), read by anyone.
  std::atomic<bool> complete{false};
  const Clock::time_point started = Clock::now();
  Clock::time_point complete_due() const {
    return started + std::chrono::duration_cast<Clock::duration>(kCompleteAfter * options.period);
  }
  bool is_deputy = false;  // discovery thread only
  // Vehicle scope, a participant in a registry that is not speaking: it follows the host's
  // vehicle table (follow_table) unless it found none current for kFallbackAfter, then it
  // listens to the group itself until one is current again (docs/discovery.md "Vehicle table").
  std::atomic<bool> listening_fallback{false};
  // Vehicle scope: speaking for this host while its speaker, alive (it holds the lock), is
  // silent on the group (stopped); held with the acting lock (docs/discovery.md "Speaker").
  bool acting = false;  // discovery thread only
  Clock::time_point acting_since{};
  off_t acting_byte = 0;
  // Under mutex: when this host's speaker was last heard on the group (a heartbeat or an index
  // of our registry), and when one that is not us was.
  Clock::time_point own_heard = started, other_speaker_heard{};
  std::uint64_t observer_periods = 0;

  // Orders what on_change is told (see the comment in the header of this class's users):
  // taken around a change of the table *and* its callback. Lock order: deliver_mutex, then mutex.
  std::mutex deliver_mutex;
  mutable std::mutex mutex;  // guards peers, counters, hosts, bound, speak-side request state
  struct Peer {
    Participant p;
    std::int64_t host = 0;    // remote: its host's id; 0: from the registry
    std::size_t bytes = 0;
    std::int32_t sent_lease = 0;  // remote: the lease its record said (p.beacon's is its host's;
                                  // as_sent() puts it back)
  };
  // A remote peer's record as it came (a base for compressed batches; the vehicle cache).
  static lcmx_msgs::beacon_t as_sent(const Peer& p) {
    auto b = p.p.beacon;
    b.lease_ms = p.sent_lease;
    return b;
  }
  std::map<std::int64_t, Peer> peers;
  std::size_t table_bytes = 0;
  Counters counters;
  Clock::time_point last_malformed_log{}, last_refused_log{}, last_send_error_log{}, last_forged_log{},
      last_twin_log{};

  // ---- registry reader (discovery thread only)
  struct Known {
    std::uint64_t state = 0;
    std::int64_t id = 0;
    std::uint64_t seq = ~0ull;        // slot revision of the last read (or skip)
    std::uint64_t stats_seq = ~0ull;
    std::uint64_t host_struct = 0;
    bool told = false;                // on_change knows it
    bool skipped = false;             // its topics do not concern us (not read)
    bool dead = false;                // its process is gone (lock free), its slot not yet reclaimed
  };
  std::vector<Known> known;
  std::uint32_t seen_changes = 0;
  Clock::time_point last_pass{};
  // The start times of the last kPassBurst passes (a ring, oldest at pass_ring_next): the next
  // pass is due kPassBurst * kCoalesce after the oldest of them (next_pass_at).
  std::array<Clock::time_point, kPassBurst> pass_ring{};
  std::size_t pass_ring_next = 0;
  Clock::time_point next_pass_at() const { return pass_ring[pass_ring_next] + kPassBurst * kCoalesce; }
  std::vector<std::string> own_topics;
  bool wildcard = false;  // reads every participant (observer, bridge, pattern subscriptions, speaker)
  std::uint64_t own_struct = 0, own_stats = 0;

  // ---- speaker (discovery thread only, except the request state under mutex)
  off_t speaker_byte = 0;
  struct Spoken {
    std::uint32_t slot = 0;
    std::int64_t revision = 0;  // the record's: the registry revision when its shape last changed
    std::uint64_t shape = 0;    // vehicle scope: structural hash of vehicle_view() (never 0)
    std::vector<std::byte> record;  // as the participant wrote it (answers to an observer's query)
    std::vector<std::byte> view;    // vehicle scope: vehicle_view(), what other hosts are sent
    Clock::time_point sent{};  // last sent in a batch without a base (send_record)
    // Vehicle scope: the view last sent on the group and its revision: what every receiver
    // that heard it holds (a base for the next batch: Batch::base).
    std::vector<std::byte> sent_view;
    std::int64_t sent_revision = 0;
  };
  std::map<std::int64_t, Spoken> spoken;      // what this speaker speaks for
  std::map<std::int64_t, std::int64_t> spoken_set;  // id -> revision (digest)
  std::set<std::int64_t> pending_records, pending_goodbyes;
  Clock::time_point flush_at = Clock::time_point::max();
  Clock::time_point last_flush{};  // the last time pending records went out
  // When changed records go out: at once if none went for kRecordDelay (a single change, e.g.
  // a subscriber that matched a bridge republisher, reaches other hosts in a millisecond, as
  // the publisher's choice of path needs), else kRecordDelay after the first of a burst (a
  // launch of many processes goes out in few datagrams). A participant's first record waits
  // kRecordDelay too: a runtime writes it when created, before its endpoints, which follow
  // within milliseconds (sent at once, the small robot's cold start sent every participant's
  // record twice, 30 ms apart, the first with no endpoints).
  void schedule_flush(bool first_record = false) {
    if (flush_at != Clock::time_point::max()) return;
    const auto now = Clock::now();
    flush_at = !first_record && now - last_flush >= kRecordDelay ? now : now + kRecordDelay;
  }
  bool want_index = false, want_all = false, want_views = false;  // under mutex
  std::set<std::int64_t> wanted;               // under mutex
  Clock::time_point last_index{}, last_all{}, last_views{}, audience_until{};
  Clock::time_point next_heartbeat{};
  struct Watch {
    int fd = -1;
    std::int64_t id = 0;
    std::uint64_t state = 0;
  };
  std::map<std::uint32_t, Watch> watches;  // slot -> pidfd
  const std::uint64_t own_pidns = pid_namespace();

  // ---- remote hosts (under mutex)
  struct RemoteHost {
    std::int64_t registry_id = 0;
    std::int64_t speaker = 0;
    std::int64_t last_sequence = 0;
    Clock::time_point last_heard{};
    std::chrono::milliseconds lease{1500};
    std::int64_t digest = 0;
    int mismatches = 0;
    Clock::time_point last_request{};
    std::map<std::int64_t, std::int64_t> members;  // participant -> revision
    std::int64_t listed_digest = 0;  // a follower: the vehicle table's listed_digest of it, taken
  };
  std::map<std::int64_t, RemoteHost> hosts;
  std::map<std::int64_t, std::uint32_t> bound;  // host id -> the address its speakers send from
  struct Request {
    std::int64_t host;
    std::vector<std::pair<std::int64_t, std::int64_t>> wanted;  // (participant, revision); empty: index
    Clock::time_point due;  // now + a random part of kRequestJitter
  };
  std::vector<Request> requests;  // to send, under mutex (send_requests: the discovery thread)
  // Requests heard on the group (anyone's, ours too), per known host: what was asked and
  // when. A request of ours for what was asked less than half a period ago is not sent: the
  // speaker's multicast answer serves us too (and it answers a record at most that often).
  struct Heard {
    Clock::time_point index{};
    std::map<std::int64_t, Clock::time_point> records;
  };
  std::map<std::int64_t, Heard> heard;  // under mutex; only hosts in `hosts`
  std::uint64_t jitter_state = random_participant_id() | 1;  // under mutex (xorshift)
  Clock::time_point request_due() {
    jitter_state ^= jitter_state << 13, jitter_state ^= jitter_state >> 7, jitter_state ^= jitter_state << 17;
    const auto span = std::chrono::duration_cast<Clock::duration>(kRequestJitter).count();
    return Clock::now() + Clock::duration(static_cast<Clock::rep>(jitter_state % static_cast<std::uint64_t>(span + 1)));
  }

  Impl(Options o, LocalFn l, ChangeFn c)
      : options(std::move(o)), local(std::move(l)), on_change(std::move(c)),
        group(options.shared_group ? options.shared_group
                                   : std::make_shared<udpm::Group>(udpm::Group::open(options.group))),
        receive(!options.shared_group) {
    host_scope = options.scope == beacon_t::SCOPE_HOST;
    group_hash = reg::group_hash(group->config());
    wake_fd = ::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
    if (wake_fd < 0) throw std::runtime_error("discovery: eventfd failed");
    registry = options.registry;
    if (!registry && (host_scope || !options.observer)) {
      RegistryOptions ro;
      ro.group = group->config();
      ro.slots = options.registry_slots;
      ro.directory = options.registry_directory;
      registry = Registry::open(ro);
    }
    own_host = registry ? registry->host_id() : host_id();
    if (registry) {
      reg = &registry->impl();
      known.resize(reg->slot_count);
    }
    const auto group_bits = static_cast<off_t>(group_hash & ((std::uint64_t{1} << 40) - 1));
    speaker_byte = host_scope ? reg::kLockSpeaker : reg::kLockVehicle + group_bits;
    acting_byte = reg::kLockVehicleActing + group_bits;
    wildcard = options.observer;
  }
  ~Impl() {
    for (auto& [i, w] : watches)
      if (w.fd >= 0) ::close(w.fd);
    if (wake_fd >= 0) ::close(wake_fd);
  }

  void wake() {
    const std::uint64_t one = 1;
    [[maybe_unused]] auto n = ::write(wake_fd, &one, sizeof one);
    wake_word.fetch_add(1, std::memory_order_release);
    shm::futex_wake_all_private(&wake_word);
  }

  std::chrono::milliseconds lease_of(std::int32_t ms) const {
    return std::chrono::milliseconds(std::clamp<std::int64_t>(ms, 1, options.max_lease.count()));
  }

  template <class... A>
  void warn_limited(Clock::time_point& last, fmt::format_string<A...> f, A&&... a) {
    const auto now = Clock::now();
    if (now - last < std::chrono::seconds(5)) return;
    last = now;
    spdlog::warn(f, std::forward<A>(a)...);
  }

  // Every discovery datagram this Discovery sends counts in udp_sent; a host_beacon_t carries
  // the count it is sent as (its `sequence`: what a listener may use to see what it missed of
  // a speaker's discovery). UDP data loss is settled per channel from the runtime's data
  // markers (lcmx_msgs::marker_t), not from these.
  void publish_udp(const std::vector<std::byte>& bytes) {
    ++udp_sent;
    try {
      group->publish(kBeaconChannel, bytes);
      std::lock_guard lock(mutex);
      ++counters.beacons_sent;
    } catch (const std::exception& e) {
      std::lock_guard lock(mutex);
      warn_limited(last_send_error_log, "lcmx discovery: cannot send (will keep trying): {}", e.what());
    }
  }

  // ------------------------------------------------------------ this participant
  // Discovery thread: builds our beacon and puts it into the registry (a structural change
  // bumps the revision and wakes those it concerns; statistics alone, once per period at most).
  void publish_local(bool periodic) {
    if (options.observer || !reg) return;
    beacon_t b = local();
    if (b.participant_id == 0) return;  // the owner is going away
    self_id = b.participant_id;
    if (!joined_registry) {
      reg->join(b.participant_id, static_cast<std::int32_t>(options.lease.count()),
                static_cast<std::int32_t>(options.period.count()));
      joined_registry = true;
    }
    b.version = kBeaconVersion;
    b.pid = static_cast<std::int32_t>(::getpid());
    b.start_time = static_cast<std::int64_t>(process_start_time(b.pid));
    b.pid_namespace = static_cast<std::int64_t>(own_pidns);
    b.sequence = ++sequence;
    b.lease_ms = static_cast<std::int32_t>(options.lease.count());
    b.scope = options.scope;
    b.timestamp_us = std::chrono::duration_cast<std::chrono::microseconds>(
                         std::chrono::system_clock::now().time_since_epoch())
                         .count();
    const auto st = structural_hash(b);
    // Statistics are rewritten (no revision bump: nobody is woken) at most once per period and
    // only when they changed; observers read them (a tool's first look is at most a period old).
    const auto stats = stats_hash(b);
    if (st == own_struct && !(periodic && stats != own_stats)) {
      reg->heartbeat();
      return;
    }
    own_stats = stats;
    const bool structural = st != own_struct;
    own_struct = st;
    reg::TopicFilter topics;
    std::vector<std::string> names;
    for (const auto& e : b.endpoints) {
      topics.add(e.topic);
      names.push_back(e.topic);
    }
    std::uint32_t flags = static_cast<std::uint8_t>(b.flags);
    if (b.flags & (beacon_t::FLAG_BRIDGE | beacon_t::FLAG_CHANNELS | beacon_t::FLAG_DDS_GATEWAY))
      flags |= reg::kSlotWildcard;
    reg->publish(!host_scope, encode_beacon(b), st, host_scope ? &topics : nullptr, flags,
                 host_scope ? 0 : group_hash);
    reg->heartbeat();
    if (structural) {
      std::sort(names.begin(), names.end());
      names.erase(std::unique(names.begin(), names.end()), names.end());
      const bool wc = (flags & reg::kSlotWildcard) != 0;
      if (names != own_topics || wc != wildcard) {
        own_topics = std::move(names);
        own_bits.clear();
        std::set<std::uint16_t> words;
        for (const auto& t : own_topics) {
          own_bits.push_back(reg::topic_bits(t));
          words.insert(own_bits.back().bit[0]);
        }
        bucket_tokens.clear();
        if (host_scope)
          for (auto w : words)
            bucket_tokens.push_back({&reg->buckets[w], reg->buckets[w].load(std::memory_order_acquire), false});
        wildcard = wc || options.observer;
        // Participants (of this host, or in the vehicle table) skipped before may concern us now.
        if (host_scope) recheck_skipped = true;
        else table_recheck = true;
      }
    }
    std::lock_guard lock(mutex);
    ++counters.beacons_sent;
  }

  // ------------------------------------------------------------ registry reader
  // Whether slot i's participant may concern us (its topic filter meets our topics).
  bool concerns(const reg::Slot& s) const {
    return concerns(s.flags.load(std::memory_order_relaxed),
                    [&](std::uint16_t w) { return s.topics[w].load(std::memory_order_relaxed); });
  }
  // The same for a record of the vehicle table (its flags and topic filter as its speaker wrote them).
  bool concerns(const table::Record& r) const {
    return concerns(r.flags, [&](std::uint16_t w) { return r.topics[w]; });
  }
  template <class Word>
  bool concerns(std::uint32_t flags, Word word) const {
    if (wildcard) return true;
    if (flags & reg::kSlotWildcard) return true;
    for (const auto& t : own_bits) {
      bool all = true;
      for (auto bit : t.bit)
        if (!(word(static_cast<std::uint16_t>(bit / 64)) & (std::uint64_t{1} << (bit % 64)))) {
          all = false;
          break;
        }
      if (all) return true;
    }
    return false;
  }
  std::vector<reg::TopicBits> own_bits;
  // What a non-wildcard reader sleeps on: the words of its topics' first filter bits.
  std::vector<shm::WaitToken> bucket_tokens;
  bool sleep_on_buckets() const { return !wildcard && !is_speaker && !own_bits.empty() && own_bits.size() < 120; }

  void tell(Change c, Participant p) {
    // deliver_mutex held by the caller
    if (on_change) on_change(c, p);
  }

  void forget_known(std::uint32_t i, std::vector<std::pair<Change, Participant>>& out) {
    auto& k = known[i];
    someone_left = true;
    if (k.told) {
      std::lock_guard lock(mutex);
      auto it = peers.find(k.id);
      if (it != peers.end() && it->second.host == 0) {
        table_bytes -= it->second.bytes;
        out.emplace_back(Change::left, std::move(it->second.p));
        peers.erase(it);
      }
    }
    if (is_speaker && k.id != 0 && spoken.erase(k.id)) {
      spoken_set.erase(k.id);
      pending_records.erase(k.id);
      pending_goodbyes.insert(k.id);
      schedule_flush();
    }
    k = Known{};
  }

  // Discovery thread: a pass over the registry. Incremental: only the slots the change log
  // names since our last pass (and those to retry); full (every slot in use): every period
  // (leases are judged), after our own topics changed, and when we fell behind the log. Cost
  // per slot visited: a few loads, plus a state file read when its revision changed and its
  // topics concern us.
  void registry_pass() {
    if (!reg) return;
    seen_changes = reg->header->changes.load(std::memory_order_acquire);  // pairs with bump_changes
    for (auto& t : bucket_tokens) t.expected = t.word->load(std::memory_order_acquire);  // likewise
    last_pass = Clock::now();
    bool full = full_due || recheck_skipped;
    const bool recheck = recheck_skipped;
    full_due = recheck_skipped = false;
    std::vector<std::uint32_t> todo(retry.begin(), retry.end());
    retry.clear();
    const auto head = reg->header->log_head.load(std::memory_order_acquire);
    if (!full) {
      if (head - log_pos > reg::kLogSize) full = true;
      for (auto p = log_pos; !full && p < head; ++p) {
        // acquire: pairs with bump_changes' release store of the entry.
        const auto e = reg->log[p % reg::kLogSize].load(std::memory_order_acquire);
        const auto expected = p & ((std::uint64_t{1} << 44) - 1);
        if (e == ~0ull || (e >> 20) < expected) {  // reserved, not yet written: again soon
          retry_soon = true;
          break;
        }
        if ((e >> 20) != expected) {  // overwritten: we fell behind
          full = true;
          break;
        }
        todo.push_back(static_cast<std::uint32_t>(e & 0xfffff));
        log_pos = p + 1;
      }
    }
    if (full) log_pos = head;
    const auto hw = std::min(reg->header->high_water.load(std::memory_order_acquire), reg->slot_count);
    if (full) {
      todo.resize(hw);
      for (std::uint32_t i = 0; i < hw; ++i) todo[i] = i;
    } else {
      std::sort(todo.begin(), todo.end());
      todo.erase(std::unique(todo.begin(), todo.end()), todo.end());
    }
    const auto now = reg::now_ns();
    std::vector<std::pair<Change, Participant>> out;
    std::unique_lock order(deliver_mutex);
    full_pass = full;
    for (auto i : todo)
      if (i < reg->slot_count) visit(i, now, recheck, out);
    for (auto& [c, p] : out) {
      if (c == Change::left)
        spdlog::debug("lcmx discovery: participant {} ({} pid {}) left", p.beacon.participant_id,
                      p.beacon.process_name, p.beacon.pid);
      tell(c, std::move(p));
    }
    order.unlock();  // (a new vehicle speaker takes the vehicle table: follow_table locks it)
    if (someone_left && !is_deputy && !is_speaker) try_speak();  // the deputy may have been the one
    someone_left = false;
  }

  void visit(std::uint32_t i, std::int64_t now, bool recheck, std::vector<std::pair<Change, Participant>>& out) {
    auto& s = reg->slot(i);
    auto& k = known[i];
    const auto st = s.state.load(std::memory_order_acquire);  // pairs with join's release
    if (reg::state_of(st) != reg::kLive) {
      if (k.id != 0 && k.told) {
        std::lock_guard lock(mutex);
        // Freed by its owner (a clean exit: its goodbye), or dead (its process exited).
        if (reg::state_of(st) == reg::kFree && reg::epoch_of(st) == reg::epoch_of(k.state) + 1) ++counters.goodbyes;
        else ++counters.exits_seen;
      }
      if (k.id != 0) forget_known(i, out);
      return;
    }
    const auto id = s.participant_id.load(std::memory_order_relaxed);
    if (id == self_id.load()) {
      // The speaker speaks for itself too (its own state, never told to on_change).
      const auto seq = s.seq.load(std::memory_order_acquire);  // pairs with publish's release
      if (!is_speaker || (k.id == id && k.seq == s.revision.load(std::memory_order_relaxed))) return;
      if (auto state = reg->read_state(i, id, seq)) {
        k.id = id;
        k.state = st;
        k.seq = state->revision;
        speak_update(id, *state, static_cast<std::int64_t>(state->revision), s.vehicle_group.load(std::memory_order_relaxed), i);
      } else {
        retry.insert(i);
        retry_soon = true;
      }
      return;
    }
    if (k.id != 0 && (k.state != st || k.id != id)) forget_known(i, out);  // reused slot
    const auto lease = lease_of(s.lease_ms.load(std::memory_order_relaxed));
    const auto age = now - s.heartbeat_ns.load(std::memory_order_relaxed);
    // Missed two heartbeats: dead, or only stopped? Its liveness lock tells (one syscall, on
    // full passes only). A dead one is gone now even if no speaker runs (the speaker itself
    // was stopped): its slot stays until a speaker reclaims it.
    const auto late = 2 * std::int64_t{s.period_ms.load(std::memory_order_relaxed)} * 1000000 + 50000000;
    if (k.id != 0 && k.told && full_pass && age > late && !reg->owner_alive(i)) {
      {
        std::lock_guard lock(mutex);
        ++counters.exits_seen;
      }
      forget_known(i, out);
      k.id = id;
      k.state = st;
      k.seq = s.revision.load(std::memory_order_relaxed);
      k.dead = true;
      return;
    }
    if (k.dead && k.id == id && k.state == st) return;  // dead, not reclaimed yet
    if (age > std::chrono::duration_cast<std::chrono::nanoseconds>(lease).count()) {
      if (k.id != 0) {
        if (k.told) {
          std::lock_guard lock(mutex);
          ++counters.leases_expired;
        }
        forget_known(i, out);  // stopped or hung: back when its heartbeat is
      }
      return;
    }
    // seq for a consistent read; the revision (structural) and stats_seq (observers) for news.
    const auto seq = s.seq.load(std::memory_order_acquire);  // pairs with publish's release
    const auto rev = s.revision.load(std::memory_order_relaxed);
    const auto stats = s.stats_seq.load(std::memory_order_relaxed);
    const bool observer_refresh = options.observer && k.told && stats != k.stats_seq;
    if (k.id == id && k.seq == rev && !observer_refresh && !(recheck && k.skipped)) return;
    if (seq & 1) {  // being written: again soon
      retry.insert(i);
      retry_soon = true;
      return;
    }
    k.state = st;
    k.id = id;
    const bool tell_it = k.told || concerns(s);
    if (!tell_it && !is_speaker) {
      k.seq = rev;
      k.skipped = true;
      std::lock_guard lock(mutex);
      ++counters.registry_skipped;
      return;
    }
    auto state = reg->read_state(i, id, seq);
    if (!state) {
      retry.insert(i);
      retry_soon = true;
      return;
    }
    {
      std::lock_guard lock(mutex);
      ++counters.registry_reads;
    }
    k.seq = state->revision;
    k.stats_seq = stats;
    k.skipped = !tell_it;
    if (is_speaker)
      speak_update(id, *state, static_cast<std::int64_t>(state->revision),
                   s.vehicle_group.load(std::memory_order_relaxed), i);
    if (!host_scope || state->host.empty() || !tell_it) return;  // vehicle scope: this host is known through the host scope
    if (k.told && state->host_struct == k.host_struct && !observer_refresh) return;
    std::string why;
    auto b = decode_beacon(state->host, &why);
    if (!b) {
      std::lock_guard lock(mutex);
      ++counters.malformed;
      warn_limited(last_malformed_log, "lcmx discovery: ignored the registry state of participant {}: {}", id, why);
      return;
    }
    if (b->participant_id != id) return;
    b->revision = static_cast<std::int64_t>(state->revision);
    b->lease_ms = static_cast<std::int32_t>(lease.count());
    k.host_struct = state->host_struct;
    Participant p{std::move(*b), Clock::now()};
    Change c;
    {
      std::lock_guard lock(mutex);
      auto [it, fresh] = peers.try_emplace(id);
      c = fresh ? Change::joined : Change::updated;
      table_bytes += state->host.size() - it->second.bytes;
      it->second.p = p;
      it->second.host = 0;
      it->second.bytes = state->host.size();
      ++counters.beacons_received;
    }
    k.told = true;
    out.emplace_back(c, std::move(p));
  }
  std::uint64_t log_pos = 0;
  bool full_due = true, recheck_skipped = false, retry_soon = false, someone_left = false, full_pass = false;
  std::set<std::uint32_t> retry;

  // ------------------------------------------------------------ speaker
  // vehicle: only participants of our vehicle group (the slot names it) are spoken for.
  void speak_update(std::int64_t id, const reg::State& state, std::int64_t revision, std::uint64_t vehicle_group,
                    std::uint32_t slot) {
    const auto& section = host_scope ? state.host : state.vehicle;
    if (section.empty() || (!host_scope && vehicle_group != group_hash)) {
      if (spoken.erase(id)) {
        spoken_set.erase(id);
        pending_goodbyes.insert(id);
      }
      return;
    }
    auto& sp = spoken[id];
    const bool first = sp.record.empty();
    sp.slot = slot;
    // Host scope: every revision. Vehicle scope: only a change of what other hosts use
    // (vehicle_view): a local match, statistics or a change of the host section alone keep
    // the record's revision and send nothing (the record is refreshed, for answers).
    std::optional<beacon_t> view;
    if (!host_scope) view = vehicle_view(section);
    const std::uint64_t shape = view ? structural_hash(*view) | 1 : 0;  // 0: not decoded, every update sent
    const bool changed = sp.record.empty() || (host_scope ? sp.revision != revision : shape != sp.shape || shape == 0);
    if (changed) {
      sp.revision = revision;
      sp.shape = shape;
    }
    sp.record = section;
    patch_revision(sp.record, sp.revision);
    if (view) {
      view->revision = sp.revision;
      sp.view = encode_beacon(*view);
    } else {
      sp.view.clear();
    }
    spoken_set[id] = sp.revision;
    if (changed) {
      pending_records.insert(id);
      pending_goodbyes.erase(id);
      schedule_flush(first);
    }
  }

  bool audience() const { return !host_scope || Clock::now() < audience_until; }

  host_beacon_t host_message(std::int8_t kind) {
    host_beacon_t h{};
    h.version = kHostBeaconVersion;
    h.kind = kind;
    h.scope = options.scope;
    h.host_id = static_cast<std::int64_t>(own_host);
    h.registry_id = reg ? static_cast<std::int64_t>(reg->header->registry_id) : 0;
    h.speaker = self_id.load();
    h.sequence = udp_sent + 1;  // the datagram it is about to be (publish_udp)
    h.lease_ms = static_cast<std::int32_t>(options.lease.count());
    h.digest = static_cast<std::int64_t>(digest_of(spoken_set));
    h.count = static_cast<std::int32_t>(spoken_set.size());
    h.num_entries = 0;
    h.num_wanted = 0;
    return h;
  }

  void send_index() {
    auto h = host_message(host_beacon_t::KIND_INDEX);
    for (const auto& [id, rev] : spoken_set) {
      h.participants.push_back(id);
      h.revisions.push_back(rev);
    }
    h.num_entries = static_cast<std::int32_t>(h.participants.size());
    publish_udp(encode_host_beacon(h));
    last_index = Clock::now();
  }

  // The records and goodbyes of one speaker pass go out together (records_t, docs/discovery.md
  // "Batches"): every process of every other host that hears the group wakes once per batch,
  // not once per record. Discovery thread.
  struct Batch {
    std::vector<std::vector<std::byte>> items;  // encode_beacon()'s bytes
    std::size_t bytes = kBatchHeaderBytes;      // the records_t they make
    std::uint64_t host = 0;                     // every record of a batch names one host
    // Compressed against this record, if set (choose_base: flushes on the vehicle group only).
    std::int64_t base_id = 0, base_revision = 0;
    std::vector<std::byte> base;
  };
  // `last`: the last batch of a pass, which carries the speaker's heartbeat as of its records
  // (docs/discovery.md "Batches"; built just before it goes out: its `sequence` counts it).
  void batch_send(Batch& b, bool last = false) {
    if (b.items.empty()) return;
    const auto heartbeat = last ? encode_host_beacon(host_message(host_beacon_t::KIND_HEARTBEAT)) : std::vector<std::byte>{};
    // The smallest of: a record alone (beacon_t), the records_t, the records_t compressed.
    const BatchBase base{b.base_id, b.base_revision, b.base};
    publish_udp(encode_batch(b.host, b.items, heartbeat, &base));  // (no bytes: no base)
    b.items.clear();  // the next batch of the pass: the same base
    b.bytes = kBatchHeaderBytes;
  }
  // The base of a flush's batches (vehicle scope): the previous revision, as sent, of the first
  // record to go (the same participant: what changed is a match or an endpoint), else the
  // record sent last (another process of this host, most likely of the same program). Only a
  // record every receiver that heard the group holds: one sent on it and not gone since.
  void choose_base(Batch& b, std::int64_t first) {
    if (host_scope) return;
    const Spoken* pick = nullptr;
    std::int64_t id = 0;
    if (auto it = spoken.find(first); it != spoken.end() && !it->second.sent_view.empty())
      pick = &it->second, id = first;
    else if (auto last = spoken.find(last_sent); last != spoken.end() && !last->second.sent_view.empty())
      pick = &last->second, id = last_sent;
    if (!pick) return;
    b.base_id = id;
    b.base_revision = pick->sent_revision;
    b.base = pick->sent_view;
  }
  void batch_add(Batch& b, std::vector<std::byte> record) {
    if (record.size() < kBeaconHostAt + 8) return;  // (encode_beacon's bytes always hold more)
    const auto n = record.size() - 8;  // nested: without its fingerprint
    const auto host = host_at(record, kBeaconHostAt);
    if (!b.items.empty() && (b.bytes + n > kBatchBytes || host != b.host)) batch_send(b);
    b.host = host;
    b.items.push_back(std::move(record));
    b.bytes += n;
    if (b.bytes > kBatchBytes) batch_send(b);  // a record larger than a batch goes alone
  }

  // `full`: the record as its participant wrote it (an observer's query), else, on the vehicle
  // group, what other hosts use of it (vehicle_view).
  void send_record(Batch& batch, std::int64_t id, bool full = false) {
    auto it = spoken.find(id);
    if (it == spoken.end()) return;
    const auto& sp = it->second;
    // `sent` rate-limits answers (twice per period: one multicast answer serves everyone);
    // a record that went against a base did not reach who lacks the base, who may be asking.
    if (batch.base.empty()) it->second.sent = Clock::now();
    batch_add(batch, full || sp.view.empty() ? sp.record : sp.view);
    if (!full && !sp.view.empty()) {
      it->second.sent_view = sp.view;
      it->second.sent_revision = sp.revision;
      last_sent = id;
    }
  }
  std::int64_t last_sent = 0;  // the participant whose view went last (choose_base)

  void send_goodbye(Batch& batch, std::int64_t id) {
    beacon_t b{};
    b.version = kBeaconVersion;
    b.participant_id = id;
    b.host_id = static_cast<std::int64_t>(own_host);
    b.flags = beacon_t::FLAG_GOODBYE;
    b.scope = options.scope;
    batch_add(batch, encode_beacon(b));
  }

  // Discovery thread, while speaking.
  void speaker_duties() {
    const auto now = Clock::now();
    watch_processes();
    if (now >= next_heartbeat) {
      publish_udp(encode_host_beacon(host_message(host_beacon_t::KIND_HEARTBEAT)));
      next_heartbeat = now + options.period;
    }
    bool index = false, all = false, views = false;
    std::set<std::int64_t> want;
    {
      std::lock_guard lock(mutex);
      // Rate limits: the index and "everything" at most once per period each; one answer, multicast, serves all.
      if (want_index && now - last_index >= options.period) index = true, want_index = false;
      if (want_all && now - last_all >= options.period) all = true, want_all = false;
      if (want_views && now - last_views >= options.period) views = true, want_views = false;
      want.swap(wanted);
    }
    Batch batch;  // this pass's records and goodbyes
    if (all) {
      // An observer's "everything": with the statistics as they are now (re-read).
      for (auto& [id, sp] : spoken) {
        const auto& slot = reg->slot(sp.slot);
        if (slot.participant_id.load(std::memory_order_relaxed) != id) continue;
        if (auto st = reg->read_state(sp.slot, id, slot.seq.load(std::memory_order_acquire))) {
          auto& section = host_scope ? st->host : st->vehicle;
          if (!section.empty()) {
            sp.record = std::move(section);
            patch_revision(sp.record, sp.revision);
          }
        }
      }
      for (const auto& [id, sp] : spoken) send_record(batch, id, true);
      last_all = now;
      index = true;
    } else if (views) {
      // A receiver that holds none of ours: every record (what other hosts use of it), and the
      // batch's heartbeat, instead of the index it would ask for and then every record.
      for (const auto& [id, sp] : spoken) send_record(batch, id);
      last_views = now;
    } else {
      for (auto id : want)
        if (auto it = spoken.find(id); it != spoken.end() && now - it->second.sent >= options.period / 2)
          send_record(batch, id);
    }
    if (now >= flush_at) {
      flush_at = Clock::time_point::max();
      last_flush = now;
      if (audience() && !(pending_records.empty() && pending_goodbyes.empty())) {
        // Its own batches, compressed against a base (answers to requests go without one:
        // who asks may lack it), after the answers' batch.
        batch_send(batch);
        if (!pending_records.empty()) choose_base(batch, *pending_records.begin());
        for (auto id : pending_records) send_record(batch, id);
        for (auto id : pending_goodbyes) send_goodbye(batch, id);
      }
      pending_records.clear();
      pending_goodbyes.clear();
    }
    // No index after the records: their batch ends with a heartbeat, and a receiver that holds
    // them and disagrees asks for the index (on_host_state). Before 2026-11-29 an index followed
    // every flush: a third of the small robot's cold-start bytes.
    batch_send(batch, true);
    if (index) send_index();
    if (all || index || views || !want.empty()) {
      std::lock_guard lock(mutex);
      ++counters.requests_answered;
    }
  }

  // Host scope speaker: a pidfd per participant of our pid namespace; others (and a backup
  // for all) by their slot's liveness lock. A dead participant's slot is reclaimed.
  void watch_processes() {
    if (!host_scope || !reg) return;
    const auto hw = std::min(reg->header->high_water.load(std::memory_order_acquire), reg->slot_count);
    const auto now = reg::now_ns();
    std::vector<std::pair<std::uint32_t, std::uint64_t>> dead;
    for (std::uint32_t i = 0; i < hw; ++i) {
      auto& s = reg->slot(i);
      const auto st = s.state.load(std::memory_order_acquire);
      const auto state = reg::state_of(st);
      auto w = watches.find(i);
      if (w != watches.end() && (state != reg::kLive || w->second.state != st)) {
        if (w->second.fd >= 0) ::close(w->second.fd);
        watches.erase(w);
        w = watches.end();
      }
      if (state == reg::kClaimed) {
        if (now - s.heartbeat_ns.load(std::memory_order_relaxed) > kClaimTimeoutNs && !reg->owner_alive(i))
          dead.emplace_back(i, st);
        continue;
      }
      if (state == reg::kDead) {  // a speaker died while reclaiming: finish it
        dead.emplace_back(i, st);
        continue;
      }
      if (state != reg::kLive || s.participant_id.load(std::memory_order_relaxed) == self_id.load()) continue;
      if (w == watches.end()) {
        Watch nw;
        nw.state = st;
        nw.id = s.participant_id.load(std::memory_order_relaxed);
        const auto pid = s.pid.load(std::memory_order_relaxed);
        const auto start = s.start_time.load(std::memory_order_relaxed);
        if (pid > 0 && s.pid_namespace.load(std::memory_order_relaxed) == own_pidns) {
          const int fd = static_cast<int>(::syscall(SYS_pidfd_open, pid, 0));
          if (fd >= 0 && process_start_time(pid) == static_cast<std::uint64_t>(start)) {
            nw.fd = fd;
          } else {
            if (fd >= 0) ::close(fd);
            if (!reg->owner_alive(i)) dead.emplace_back(i, st);
          }
        }
        watches[i] = nw;
      }
    }
    // Which watched processes exited (poll, no wait).
    std::vector<pollfd> fds;
    std::vector<std::uint32_t> slots;
    for (const auto& [i, w] : watches)
      if (w.fd >= 0) fds.push_back({w.fd, POLLIN, 0}), slots.push_back(i);
    if (!fds.empty() && ::poll(fds.data(), fds.size(), 0) > 0)
      for (std::size_t k = 0; k < fds.size(); ++k)
        if (fds[k].revents & (POLLIN | POLLHUP | POLLERR)) dead.emplace_back(slots[k], watches[slots[k]].state);
    // Others: their liveness lock, once per period.
    if (Clock::now() >= next_lock_probe) {
      next_lock_probe = Clock::now() + options.period;
      for (const auto& [i, w] : watches)
        if (w.fd < 0 && !reg->owner_alive(i)) dead.emplace_back(i, w.state);
    }
    for (auto [i, st] : dead) {
      if (auto w = watches.find(i); w != watches.end()) {
        if (w->second.fd >= 0) ::close(w->second.fd);
        watches.erase(w);
      }
      if (reg::state_of(st) == reg::kLive && reg->owner_alive(i)) continue;  // pidfd of an exec'd... lock says alive
      reg->reclaim(i, st);  // readers count it (Counters::exits_seen) when they see it
    }
  }
  Clock::time_point next_lock_probe{};

  // Speaker election: the speaker holds an OFD lock (the kernel drops it when it dies). One
  // deputy (host scope; it holds the deputy lock) tries the speaker's lock every kSpeakerTick,
  // so a dead speaker is replaced within ~20 ms; everyone else tries the deputy's lock once per period.
  void try_speak() {
    if (options.observer || !reg || !joined_registry) return;
    if (is_speaker) return;
    if (host_scope && !is_deputy && reg->try_lock(reg::kLockDeputy)) is_deputy = true;
    if (!reg->try_lock(speaker_byte)) return;
    if (is_deputy) {
      reg->unlock(reg::kLockDeputy);
      is_deputy = false;
    }
    {
      std::lock_guard lock(mutex);
      ++counters.speaker_terms;
    }
    become_speaker();
  }

  // The speaker's duties begin: every participant is read again and spoken for.
  void become_speaker() {
    is_speaker = true;
    if (host_scope) reg->header->speaker.store(self_id.load(), std::memory_order_relaxed);
    // RLIMIT_NOFILE: a pidfd per participant of this host.
    rlimit rl{};
    if (::getrlimit(RLIMIT_NOFILE, &rl) == 0 && rl.rlim_cur < rl.rlim_max) {
      rl.rlim_cur = rl.rlim_max;
      ::setrlimit(RLIMIT_NOFILE, &rl);
    }
    // Read every participant: we speak for all of them.
    for (auto& k : known) k.seq = ~0ull;
    full_due = true;
    next_heartbeat = Clock::now();
    if (follows_table()) {
      // What the host's vehicle table holds (the previous speaker's, or an acting one's): every
      // record, whatever its topics (we write the table from now on), and the leases of its hosts
      // start now (their heartbeats reach us from now on). What it lacks is asked for as ever:
      // the next heartbeats' digests disagree.
      listening_fallback = false;
      follow_table(true);
      std::lock_guard lock(mutex);
      for (auto& [id, h] : hosts) h.last_heard = Clock::now();
      table_written_once = false;  // ours is written at once
    }
    note_listening();
    spdlog::debug("lcmx discovery: participant {} speaks for {} (scope {})", self_id.load(), reg->path,
                  static_cast<int>(options.scope));
  }

  // Vehicle scope: a speaker that holds its lock but is not heard on the group for half the
  // lease other hosts give this host (it is stopped: SIGSTOP, a debugger, a frozen cgroup)
  // would have them drop every participant of this host. One other participant (the one that
  // takes the acting lock) speaks meanwhile, from the same registry: the same records and
  // digest, so other hosts see no change but the stopped one's lease running out. It stands
  // down when it hears another speaker of this registry (the stopped one resumed) and becomes
  // the speaker when the speaker's lock comes free (it died). Discovery thread.
  Clock::duration act_after() const {
    return std::max<Clock::duration>(options.lease / 2, options.period * 5 / 2);
  }
  // A follower judges by the vehicle table: its speaker patches it every period (a stopped one
  // does not). A participant that listens to the group itself (listening_fallback: no table)
  // judges by its speaker's heartbeats (not on a group without multicast loop: there nobody
  // hears this host's speaker).
  void try_act() {
    if (host_scope || options.observer || !reg || !joined_registry || is_speaker) return;
    if (listening_fallback) {
      if (!group->config().multicast_loop) return;
      std::lock_guard lock(mutex);
      if (Clock::now() - own_heard < act_after()) return;
    } else if (Clock::now() - table_current_at < act_after()) {
      return;
    }
    if (!reg->try_lock(acting_byte)) return;
    acting = true;
    acting_since = Clock::now();
    {
      std::lock_guard lock(mutex);
      ++counters.acting_terms;
    }
    spdlog::warn("lcmx discovery: this host's speaker on the vehicle group was not heard for {} ms but holds its "
                 "lock (stopped?): participant {} speaks for {} until it is heard again",
                 std::chrono::duration_cast<std::chrono::milliseconds>(act_after()).count(), self_id.load(), reg->path);
    become_speaker();
  }
  void check_acting() {
    if (!acting) return;
    if (reg->try_lock(speaker_byte)) {  // the silent speaker died: ours now
      reg->unlock(acting_byte);
      acting = false;
      std::lock_guard lock(mutex);
      ++counters.speaker_terms;
      return;
    }
    {
      std::lock_guard lock(mutex);
      if (other_speaker_heard <= acting_since) return;
    }
    spdlog::info("lcmx discovery: this host's speaker on the vehicle group is heard again: participant {} stands down",
                 self_id.load());
    stand_down();
  }
  // Stops speaking (acting only): what it spoke for is forgotten, to be read again whenever it
  // speaks next.
  void stand_down() {
    is_speaker = false;
    acting = false;
    reg->unlock(acting_byte);
    spoken.clear();
    spoken_set.clear();
    pending_records.clear();
    pending_goodbyes.clear();
    flush_at = Clock::time_point::max();
    last_sent = 0;
    // A follower again: the table is read anew (whoever writes it now), and judged from now on.
    // If the speaker we heard has no current table (it cannot write it), this participant
    // listens to the group itself rather than act again (check_fallback undoes it once one is).
    table_generation_seen = ~0ull;
    if (table_is_current()) table_current_at = Clock::now();
    else listening_fallback = true;
    {
      std::lock_guard lock(mutex);
      own_heard = Clock::now();
      want_index = want_all = want_views = false;
      wanted.clear();
      requests.clear();
    }
    note_listening();
  }

  // ------------------------------------------------------------ the group
  // A compressed batch of host `h` against a base record we do not hold (we missed it, or
  // started after it; an observer holds full records, not what was sent): its records are
  // lost to us. Asks that host for its index now (at most once per period), then for what is
  // missing, as after a batch whose heartbeat disagrees.
  void missed_batch(std::int64_t h, std::uint32_t ip) {
    {
      std::lock_guard lock(mutex);
      ++counters.missed_batches;
      auto it = hosts.find(h);
      if (it == hosts.end() || !source_ok(h, ip)) return;
      auto& host = it->second;
      if (Clock::now() - host.last_request < options.period) return;
      host.last_request = Clock::now();
      host.mismatches = 0;
      lack(h, {});
    }
    wake();
  }

  // A datagram from the group that does not decode: counted, warned about (every 5 s at most).
  void malformed(const char* what, const std::string& why) {
    std::lock_guard lock(mutex);
    ++counters.malformed;
    warn_limited(last_malformed_log, "lcmx discovery: ignored {}: {}", what, why);
  }

  void forged(const std::string& what) {
    std::lock_guard lock(mutex);
    ++counters.forged;
    warn_limited(last_forged_log, "lcmx discovery: refused {} ({} so far)", what, counters.forged);
  }

  // Under mutex: the address host `h` speaks from; first contact binds it. False: another address.
  bool source_ok(std::int64_t h, std::uint32_t ip) {
    auto it = bound.find(h);
    if (it == bound.end()) {
      if (bound.size() >= 4096) return false;  // bounded: a flood of invented hosts
      bound[h] = ip;
      return true;
    }
    return it->second == ip;
  }

  void on_datagram(const udpm::Message& m) {
    if (m.channel != kBeaconChannel) return;
    // A follower takes other hosts from the vehicle table, not from the group (its owner's
    // receive filter normally drops these before they wake anyone: Options::on_listening).
    if (!listening()) return;
    const auto fp = fingerprint_of(m.data);
    if (fp == host_beacon_t::getHash()) return on_host_message(m);
    if (fp == lcmx_msgs::records_t::getHash() || fp == lcmx_msgs::records_z_t::getHash()) return on_records(m);
    // A record of this host's own participants (its speaker's, heard by everyone on the group):
    // known through the registry; dropped before decoding.
    if (fp == beacon_t::getHash() && host_at(m.data, kBeaconHostAt) == own_host) return;
    std::string why;
    auto b = decode_beacon(m.data, &why);
    if (!b) return malformed("a beacon", why);
    on_beacon(std::move(*b), m.source.address_be, m.data.size());
  }

  // A batch of one host's records and goodbyes (records_t, or records_z_t: compressed): each
  // as if it came alone.
  void on_records(const udpm::Message& m) {
    // This host's own (its speaker's, heard by everyone on the group): known through the
    // registry; dropped before decoding (the host id lies at the same offset in both).
    const auto batch_host = static_cast<std::int64_t>(host_at(m.data, kRecordsHostAt));
    if (static_cast<std::uint64_t>(batch_host) == own_host) return;
    // Compressed against a base record: its bytes as it came, if we hold that revision.
    const auto [base_id, base_revision] = batch_base(m.data);
    std::vector<std::byte> base;
    if (base_id != 0) {
      std::lock_guard lock(mutex);
      if (auto it = peers.find(base_id);
          it != peers.end() && it->second.host == batch_host && it->second.p.beacon.revision == base_revision)
        base = encode_beacon(as_sent(it->second));
    }
    std::string why;
    auto r = decode_batch(m.data, &why, base);
    if (!r && options.observer && !base.empty()) {
      // An observer holds the full record (its query's answer: local matches, statistics); the
      // base went as what other hosts use of it, which is the same at the same revision.
      if (auto view = vehicle_view(base)) r = decode_batch(m.data, &why, encode_beacon(*view));
    }
    if (!r && base_id != 0) return missed_batch(batch_host, m.source.address_be);
    if (!r) return malformed("a batch of records", why);
    for (auto& b : r->records) {
      const auto bytes = static_cast<std::size_t>(b.getEncodedSize());
      on_beacon(std::move(b), m.source.address_be, bytes);
    }
    for (const auto& h : r->state) on_host_state(h, m.source.address_be, true);  // as of the records above
  }

  // One beacon_t heard (alone or in a batch): an observer's query, or a record or goodbye of
  // another host. `ip` is the datagram's source, `bytes` the record's size (table bounds).
  void on_beacon(beacon_t b, std::uint32_t ip, std::size_t bytes) {
    if (b.flags & beacon_t::FLAG_QUERY) {  // an observer without the registry: everything, rate-limited
      std::lock_guard lock(mutex);
      if (is_speaker) {
        if (want_all) ++counters.requests_limited;
        want_all = true;
        audience_until = Clock::now() + 3 * options.lease;
      }
    }
    if (b.flags & (beacon_t::FLAG_OBSERVER | beacon_t::FLAG_QUERY)) {
      wake();
      return;
    }
    if (static_cast<std::uint64_t>(b.host_id) == own_host) return;  // known through the registry
    on_record(std::move(b), ip, bytes);
  }

  // Returns whether the table took it (a new participant or revision).
  bool on_record(beacon_t b, std::uint32_t ip, std::size_t bytes) {
    std::string bad = check_record(b, ip);
    if (!bad.empty()) return forged(bad), false;
    std::unique_lock order(deliver_mutex);
    auto told = apply_record(std::move(b), bytes);
    if (!told) return false;
    const bool taken = told->first != Change::left;
    if (on_change) on_change(told->first, told->second);
    std::lock_guard lock(mutex);  // (deliver_mutex still held: told before complete can latch)
    update_complete();
    return taken;
  }

  // Puts record (or goodbye) `b` of another host into the table; returns what to tell
  // on_change (nullopt: nothing new, or refused by the table's bounds). `bytes`: its encoded
  // size. deliver_mutex held by the caller (it tells what this returns before releasing it).
  std::optional<std::pair<Change, Participant>> apply_record(beacon_t b, std::size_t bytes) {
    std::lock_guard lock(mutex);
    ++counters.beacons_received;
    const auto h = b.host_id;
    auto it = peers.find(b.participant_id);
    auto& host = hosts[h];
    if (host.last_heard == Clock::time_point{}) {
      host.last_heard = Clock::now();
      host.lease = lease_of(b.lease_ms);
    }
    if (b.flags & beacon_t::FLAG_GOODBYE) {
      host.members.erase(b.participant_id);
      if (it == peers.end()) return std::nullopt;
      ++counters.goodbyes;
      auto gone = std::make_pair(Change::left, std::move(it->second.p));
      table_bytes -= it->second.bytes;
      peers.erase(it);
      return gone;
    }
    if (it != peers.end() && b.revision < it->second.p.beacon.revision) return std::nullopt;  // older
    const std::size_t old = it == peers.end() ? 0 : it->second.bytes;
    std::string refused;
    if (it == peers.end() && peers.size() >= options.max_participants)
      refused = "the table holds max_participants (" + std::to_string(options.max_participants) + ")";
    else if (table_bytes - old + bytes > options.max_table_bytes)
      refused = "the table would exceed max_table_bytes (" + std::to_string(options.max_table_bytes) + ")";
    if (!refused.empty()) {
      // A known participant keeps its place (and its host's heartbeat keeps it): never expired for this.
      ++counters.refused;
      warn_limited(last_refused_log, "lcmx discovery: refused a record of participant {}: {}; {} refused so far",
                   b.participant_id, refused, counters.refused);
      return std::nullopt;
    }
    Change change = Change::updated;
    if (it == peers.end()) {
      change = Change::joined;
      it = peers.emplace(b.participant_id, Peer{}).first;
    } else if (it->second.p.beacon.revision == b.revision && !options.observer) {
      return std::nullopt;  // nothing new (statistics are for observers)
    }
    it->second.sent_lease = b.lease_ms;
    b.lease_ms = static_cast<std::int32_t>(host.lease.count());
    host.members[b.participant_id] = b.revision;
    table_bytes += bytes - old;
    it->second.bytes = bytes;
    it->second.host = h;
    it->second.p.beacon = std::move(b);
    it->second.p.last_seen = Clock::now();
    return std::make_pair(change, it->second.p);
  }

  // Whether `id` is this process's participant or one in this host's registry (a slot in use;
  // a claimed slot may still name its previous, dead owner: refusing that id costs nothing).
  // Any thread: the registry is read with atomics only.
  bool of_this_host(std::int64_t id) const { return (id != 0 && id == self_id.load()) || slot_of(id); }
  // The slot in use that names participant `id` (null: none). Any thread (atomics only).
  const reg::Slot* slot_of(std::int64_t id) const {
    if (!reg) return nullptr;
    const auto hw = std::min(reg->header->high_water.load(std::memory_order_acquire), reg->slot_count);
    for (std::uint32_t i = 0; i < hw; ++i) {
      const auto& s = reg->slot(i);
      if (reg::state_of(s.state.load(std::memory_order_acquire)) != reg::kFree &&
          s.participant_id.load(std::memory_order_relaxed) == id)
        return &s;
    }
    return nullptr;
  }

  // The trust rules (docs/discovery.md "Trust"): a record or goodbye of host H only from the
  // address H's speakers send from (first contact binds it), its source claims only with that
  // address, a participant id only for the host that first announced it, never one of this
  // host's (this process's, or one in this host's registry: known there, not from the
  // network). Called for records of other hosts only. Returns why not ("": ok).
  std::string check_record(const beacon_t& b, std::uint32_t ip) {
    std::lock_guard lock(mutex);
    const auto h = b.host_id;
    if (!source_ok(h, ip))
      return "a record or goodbye of participant " + std::to_string(b.participant_id) + " of host " +
             std::to_string(h) + " from another address than its host's";
    // The vehicle group: its claim must name the address its host speaks from. (On the
    // host-local group every sender is of this machine, and a datagram leaves from whichever of
    // its addresses the group routes through: the runtime matches those by port.)
    if (!host_scope && !b.vehicle_source.empty() && ip_of(b.vehicle_source) != ip)
      return "the source claim '" + b.vehicle_source + "' of participant " + std::to_string(b.participant_id);
    auto it = peers.find(b.participant_id);
    if (it != peers.end() && it->second.host != h)
      return "a record of participant " + std::to_string(b.participant_id) + " claimed by another host";
    // (A known peer passed this at its first record: the registry is scanned for newcomers only.)
    if (it == peers.end() && of_this_host(b.participant_id))
      return "a record of participant " + std::to_string(b.participant_id) + " of this host claimed by host " +
             std::to_string(h);
    return {};
  }

  void on_host_message(const udpm::Message& m) {
    std::string why;
    auto h = decode_host_beacon(m.data, &why);
    if (!h) return malformed("a host beacon", why);
    if (h->kind == host_beacon_t::KIND_MARK) return;  // (data markers of builds before marker_t)
    if (h->kind == host_beacon_t::KIND_REQUEST) {
      std::lock_guard lock(mutex);
      audience_until = Clock::now() + 3 * options.lease;
      note_request(*h);
      if (!is_speaker || (h->target_host != 0 && static_cast<std::uint64_t>(h->target_host) != own_host)) return;
      if (h->wanted.empty()) {
        if (want_index) ++counters.requests_limited;
        want_index = true;
      } else if (h->wanted.size() == 1 && h->wanted[0] == host_beacon_t::WANT_VIEWS) {
        if (want_views) ++counters.requests_limited;
        want_views = true;
      } else if (h->wanted.size() == 1 && h->wanted[0] == host_beacon_t::WANT_ALL) {
        if (want_all) ++counters.requests_limited;
        want_all = true;
        // Someone watches: this host's participants keep their statistics fresh meanwhile.
        if (reg)
          reg->header->observed_until_ns.store(
              reg::now_ns() + 3 * std::chrono::duration_cast<std::chrono::nanoseconds>(options.period).count(),
              std::memory_order_relaxed);
      } else {
        for (auto id : h->wanted)
          if (wanted.size() < 65536) wanted.insert(id);
      }
      wake();
      return;
    }
    if (static_cast<std::uint64_t>(h->host_id) == own_host) {  // ourselves...
      if (reg && h->registry_id == static_cast<std::int64_t>(reg->header->registry_id) &&
          (h->kind == host_beacon_t::KIND_HEARTBEAT || h->kind == host_beacon_t::KIND_INDEX)) {
        std::lock_guard lock(mutex);  // ... our speaker (try_act, check_acting)
        own_heard = Clock::now();
        if (h->speaker != self_id.load()) other_speaker_heard = own_heard;
        return;
      }
      if (reg && h->registry_id != static_cast<std::int64_t>(reg->header->registry_id)) {
        // ... or another registry with our host id: processes given one LCMX_HOST_ID that do
        // not share /dev/shm (containers). They cannot meet: no shared memory, and their
        // records are taken for ours. Said loudly, as a misconfiguration.
        std::lock_guard lock(mutex);
        warn_limited(last_twin_log,
                     "lcmx discovery: another registry claims this host's id {} on this group (participant {} "
                     "speaks for it): processes that share LCMX_HOST_ID but not /dev/shm cannot see each other; "
                     "give each /dev/shm its own host id (theirs {:x}, ours {:x} in {})",
                     own_host, h->speaker, static_cast<std::uint64_t>(h->registry_id),
                     static_cast<std::uint64_t>(reg->header->registry_id), registry->path());
      }
      return;
    }
    on_host_state(*h, m.source.address_be, false);
  }

  // Another host's heartbeat or index from address `ip`: its table here follows (a restart,
  // members gone, records to ask for). `settled`: a heartbeat at the end of a batch, as of the
  // records just taken from it (none of them can still be on its way).
  void on_host_state(const host_beacon_t& h, std::uint32_t ip, bool settled) {
    std::vector<std::int64_t> gone;
    bool ask = false;
    {
      std::lock_guard lock(mutex);
      audience_until = Clock::now() + 3 * options.lease;  // another registry listens on this group
      if (!source_ok(h.host_id, ip))
        return (void)(++counters.forged);
      auto& host = hosts[h.host_id];
      if (host.registry_id != 0 && host.registry_id != h.registry_id) {
        // The host restarted (a new registry): its old participants are gone.
        for (const auto& [id, rev] : host.members) gone.push_back(id);
        host.members.clear();
      }
      host.registry_id = h.registry_id;
      host.speaker = h.speaker;
      host.last_heard = Clock::now();
      host.lease = lease_of(h.lease_ms);
      host.digest = h.digest;
      if (h.kind == host_beacon_t::KIND_INDEX) {
        std::set<std::int64_t> listed(h.participants.begin(), h.participants.end());
        for (const auto& [id, rev] : host.members)
          if (!listed.count(id)) gone.push_back(id);
        std::vector<std::pair<std::int64_t, std::int64_t>> want;
        for (std::size_t k = 0; k < h.participants.size(); ++k) {
          auto mine = host.members.find(h.participants[k]);
          if (mine == host.members.end() || mine->second != h.revisions[k])
            want.emplace_back(h.participants[k], h.revisions[k]);
        }
        for (auto id : gone) host.members.erase(id);
        if (!want.empty() && want.size() <= 4096) lack(h.host_id, std::move(want));
        ask = !requests.empty();
      } else if (static_cast<std::uint64_t>(h.digest) != digest_of(host.members)) {
        // Records may be on their way: ask after two heartbeats that disagree, once per period;
        // after a batch's heartbeat at once (its records came with it).
        // (Asking at the first when we hold none of that host's records made a launch of 2 x 50
        // processes send 20 % more records, newcomers asking every half period, and ended no
        // start-up window sooner: docs/discovery.md "Complete".)
        host.mismatches += settled ? 2 : 1;
        if (host.mismatches >= 2 && Clock::now() - host.last_request >= options.period) {
          host.last_request = Clock::now();
          host.mismatches = 0;
          lack(h.host_id, {});
          ask = true;
        }
      } else {
        host.mismatches = 0;
      }
    }
    drop_members(gone);
    check_complete();
    if (ask) wake();
  }

  // Latches `complete` once every host heard agrees with what we hold of it and
  // kCompleteAfter periods have passed (Discovery::complete). Cheap once latched. Under
  // deliver_mutex and mutex: every record counted in a host's members has been told to
  // on_change (on_record tells under deliver_mutex), so a publisher that sees `complete`
  // knows every subscriber those records name. check_complete takes both.
  void check_complete() {
    if (complete.load(std::memory_order_relaxed)) return;
    std::lock_guard order(deliver_mutex);
    std::lock_guard lock(mutex);
    update_complete();
  }
  void update_complete() {
    if (complete.load(std::memory_order_relaxed)) return;
    if (host_scope) {
      complete = true;
      return;
    }
    if (follower()) return;  // the vehicle table says (follow_table)
    if (Clock::now() < complete_due()) return;
    for (const auto& [id, h] : hosts)
      if (h.last_heard == Clock::time_point{} || static_cast<std::uint64_t>(h.digest) != digest_of(h.members)) return;
    complete = true;
  }

  // Under mutex: a request heard on the group (note the ids asked of a host we know).
  void note_request(const host_beacon_t& h) {
    if (h.target_host == 0 || !hosts.count(h.target_host)) return;
    auto& e = heard[h.target_host];
    const auto now = Clock::now();
    if (h.wanted.empty() || (h.wanted.size() == 1 && h.wanted[0] == host_beacon_t::WANT_VIEWS)) {
      e.index = now;  // (every record and a heartbeat serve who wants the index too)
      return;
    }
    if (h.wanted.size() == 1 && h.wanted[0] == host_beacon_t::WANT_ALL) return;
    std::erase_if(e.records, [&](const auto& kv) { return now - kv.second >= options.period; });
    for (auto id : h.wanted)
      if (e.records.size() < 4096) e.records[id] = now;
  }

  void drop_members(const std::vector<std::int64_t>& ids) {
    if (ids.empty()) return;
    std::lock_guard order(deliver_mutex);
    std::vector<Participant> left;
    {
      std::lock_guard lock(mutex);
      for (auto id : ids) {
        auto it = peers.find(id);
        if (it == peers.end() || it->second.host == 0) continue;
        table_bytes -= it->second.bytes;
        left.push_back(std::move(it->second.p));
        peers.erase(it);
      }
    }
    for (auto& p : left) tell(Change::left, std::move(p));
  }

  // Sends the requests that are due, less what came or was asked by anyone meanwhile
  // (kRequestJitter). Returns when the next one is due (max: none).
  Clock::time_point send_requests() {
    std::vector<host_beacon_t> out;
    auto next = Clock::time_point::max();
    {
      std::lock_guard lock(mutex);
      const auto now = Clock::now();
      std::erase_if(requests, [&](Request& q) {
        if (q.due > now) {
          next = std::min(next, q.due);
          return false;
        }
        const auto host = hosts.find(q.host);
        if (host == hosts.end()) return true;  // gone meanwhile
        const auto e = heard.find(q.host);
        const bool fresh_ask = e != heard.end();
        if (q.wanted.empty()) {  // the index
          if (fresh_ask && now - e->second.index < options.period / 2) {
            ++counters.requests_folded;
            return true;
          }
        } else {
          const auto before = q.wanted.size();
          std::erase_if(q.wanted, [&](const auto& w) {
            const auto mine = host->second.members.find(w.first);
            if (mine != host->second.members.end() && mine->second == w.second) return true;  // came meanwhile
            if (!fresh_ask) return false;
            const auto asked = e->second.records.find(w.first);
            return asked != e->second.records.end() && now - asked->second < options.period / 2;
          });
          if (q.wanted.size() < before) ++counters.requests_folded;
          if (q.wanted.empty()) return true;
        }
        auto h = host_message(host_beacon_t::KIND_REQUEST);
        h.target_host = q.host;
        for (const auto& w : q.wanted) h.wanted.push_back(w.first);
        // Holding none of that host's records: all of them at once, not its index first.
        if (q.wanted.empty() && host->second.members.empty()) h.wanted.push_back(host_beacon_t::WANT_VIEWS);
        h.num_wanted = static_cast<std::int32_t>(h.wanted.size());
        out.push_back(std::move(h));
        return true;
      });
    }
    for (const auto& h : out) publish_udp(encode_host_beacon(h));
    if (!out.empty()) {
      std::lock_guard lock(mutex);
      counters.requests_sent += out.size();
    }
    return next;
  }

  // An observer's query. With the registry (host scope) this host needs none: only the known
  // neighbours are asked, each by name (a query of everyone would make every participant of
  // every registry on the group hear every record). Without it: every host, at once.
  void send_query() {
    std::vector<std::int64_t> targets;
    if (reg) {
      std::lock_guard lock(mutex);
      for (const auto& [id, h] : hosts) targets.push_back(id);
    } else {
      targets.push_back(0);
    }
    for (auto t : targets) {
      auto h = host_message(host_beacon_t::KIND_REQUEST);
      h.target_host = t;
      h.wanted = {host_beacon_t::WANT_ALL};
      h.num_wanted = 1;
      h.digest = 0;
      h.count = 0;
      publish_udp(encode_host_beacon(h));
    }
  }

  void drain_queued() {
    try {
      if (receive)
        group->drain([this](const udpm::Message& m) { on_datagram(m); });
      else if (options.drain_before_expiry)
        options.drain_before_expiry();
    } catch (const std::exception& e) {
      spdlog::warn("lcmx discovery: receive failed: {}", e.what());
    }
  }

  // Hosts whose speaker fell silent for its lease: all their participants go.
  void expire_hosts() {
    auto due = [&](Clock::time_point now) {
      std::vector<std::int64_t> d;
      for (const auto& [id, h] : hosts)
        if (now - h.last_heard > h.lease) d.push_back(id);
      return d;
    };
    {
      std::lock_guard lock(mutex);
      if (due(Clock::now()).empty()) return;
    }
    for (int read = 1;; ++read) {
      // Their heartbeats may be queued still (this process was stopped and resumed): read them first.
      const auto read_at = Clock::now();
      drain_queued();
      std::vector<std::int64_t> gone;
      {
        std::lock_guard lock(mutex);
        const auto now = Clock::now();
        if (now - read_at > kStall && read < kMaxReads) continue;
        for (auto h : due(now)) {
          for (const auto& [id, p] : peers)
            if (p.host == h) gone.push_back(id), ++counters.leases_expired;
          hosts.erase(h);
          heard.erase(h);  // only hosts in `hosts` (note_request)
        }
      }
      drop_members(gone);
      return;
    }
  }

  Clock::time_point next_host_expiry() const {
    std::lock_guard lock(mutex);
    auto t = Clock::time_point::max();
    for (const auto& [id, h] : hosts) t = std::min(t, h.last_heard + h.lease + std::chrono::milliseconds(1));
    return t;
  }

  // ------------------------------------------------------------ vehicle table
  // docs/discovery.md "Vehicle table" (vehicle_table.hpp): the vehicle speaker of a host writes
  // what it holds of the other hosts (their heartbeat's state and their records, each with its
  // topic filter) into a file beside the registry; every other vehicle participant of the host
  // follows that file instead of the group: woken when it changes (Header::vehicle_changes), it
  // reads only the hosts whose records changed, and of those only the records whose topics
  // concern it. A follower with no current table for kFallbackAfter listens to the group itself
  // (as every participant did before) until one is current again.

  // Whether this Discovery has a vehicle table: vehicle scope, a participant in a registry.
  bool follows_table() const { return !host_scope && !options.observer && reg; }
  // A follower: reads the table, ignores the group's discovery.
  bool follower() const { return follows_table() && !is_speaker && !listening_fallback; }
  bool listening() const { return !follower(); }
  // Whether a table written at `written_ns` is current: within two periods (its speaker
  // rewrites it, or patches its time, every period).
  bool table_current(std::int64_t written_ns) const {
    const auto age = reg::now_ns() - written_ns;
    return age >= 0 && age <= 2 * std::chrono::duration_cast<std::chrono::nanoseconds>(options.period).count();
  }
  static constexpr int kFallbackAfter = 2;  // times act_after() without a current table

  // Tells the owner when listening() changed (Options::on_listening). Discovery thread, no lock held.
  void note_listening() {
    const bool now = listening();
    if (now == listening_told) return;
    listening_told = now;
    if (options.on_listening && follows_table()) options.on_listening(now);
  }
  bool listening_told = true;  // (a new Discovery listens until it first follows a table)

  // Under mutex: a hash of what the table holds (hosts' heartbeat state, members' revisions),
  // of every host or of those in `only`.
  std::uint64_t tables_shape(const std::set<std::int64_t>* only = nullptr) const {
    std::uint64_t h = 1469598103934665603ull;
    for (const auto& [id, host] : hosts) {
      if (only && !only->count(id)) continue;
      const std::int64_t v[5] = {id, host.registry_id, host.speaker, host.digest,
                                 static_cast<std::int64_t>(digest_of(host.members))};
      h = reg::fnv1a(std::as_bytes(std::span(v)), h);
    }
    return h;
  }

  // ---- the speaker's side (discovery thread)
  // Rewrites the table when what it holds of other hosts changed (at most once per kCoalesce),
  // and patches its time once per period anyway (a stopped or dead speaker's table goes stale).
  struct TableEntry {  // a record as it goes into the table, made again only for a new revision
    std::int64_t revision = 0;
    table::Content::Entry entry;
  };
  std::map<std::int64_t, TableEntry> table_entries;
  std::uint64_t table_shape_written = 0;  // tables_shape() (with the complete flag) of the file written
  bool table_written_once = false;
  Clock::time_point table_written{};
  std::uint64_t table_generation = 0;
  Clock::time_point last_table_error_log{};

  void write_table() {
    if (!follows_table() || !is_speaker) return;
    const auto now = Clock::now();
    const bool refresh = now - table_written >= options.period;
    if (!refresh && now - table_written < kCoalesce) return;
    std::vector<std::byte> bytes;
    {
      std::lock_guard lock(mutex);
      const auto shape = tables_shape() ^ (complete.load() ? 0x9e3779b97f4a7c15ull : 0);
      if (!table_written_once || shape != table_shape_written) {
        table::Content c;
        c.writer = self_id.load();
        c.complete = complete.load();
        std::set<std::int64_t> listed;
        for (const auto& [id, host] : hosts) {
          auto ip = bound.find(id);
          if (ip == bound.end() || host.last_heard == Clock::time_point{}) continue;
          table::Content::HostEntry he;
          he.host.host_id = id;
          he.host.registry_id = host.registry_id;
          he.host.speaker = host.speaker;
          he.host.digest = host.digest;
          he.host.address = ip->second;
          he.host.lease_ms = static_cast<std::int32_t>(host.lease.count());
          std::map<std::int64_t, std::int64_t> set;
          for (const auto& [pid, rev] : host.members) {
            auto p = peers.find(pid);
            if (p == peers.end() || p->second.host != id) continue;
            auto& te = table_entries[pid];
            if (te.entry.bytes.empty() || te.revision != p->second.p.beacon.revision) {
              te.revision = p->second.p.beacon.revision;
              te.entry = table_entry(as_sent(p->second));
            }
            he.records.push_back(te.entry);
            set[pid] = te.revision;
            listed.insert(pid);
          }
          he.host.listed_digest = static_cast<std::int64_t>(digest_of(set));
          c.hosts.push_back(std::move(he));
        }
        std::erase_if(table_entries, [&](const auto& kv) { return !listed.count(kv.first); });
        bytes = table::encode(c, own_host, ++table_generation);
        table_shape_written = shape;
      } else if (!refresh) {
        return;
      }
    }
    const bool ok = bytes.empty() ? reg->patch_table_time(group_hash, reg::now_ns()) : reg->write_table(group_hash, bytes);
    const int err = errno;
    table_written = now;
    if (ok) {
      table_written_once = table_written_once || !bytes.empty();
      return;
    }
    table_written_once = false;  // written whole next time
    std::lock_guard lock(mutex);
    warn_limited(last_table_error_log,
                 "lcmx discovery: cannot write the vehicle table {} ({}): the other participants of this host "
                 "will listen to the vehicle group themselves",
                 reg->table_path_for(group_hash), std::strerror(err));
  }

  // A record as the table holds it: its bytes as sent, its topic filter, and whether it wants
  // every topic (a bridge, a DDS gateway, a channel-pattern reader).
  static table::Content::Entry table_entry(const beacon_t& b) {
    table::Content::Entry e;
    e.participant_id = b.participant_id;
    e.revision = b.revision;
    for (const auto& ep : b.endpoints) e.topics.add(ep.topic);
    if (b.flags & (beacon_t::FLAG_BRIDGE | beacon_t::FLAG_CHANNELS | beacon_t::FLAG_DDS_GATEWAY))
      e.flags |= reg::kSlotWildcard;
    e.bytes = encode_beacon(b);
    return e;
  }

  // ---- the followers' side (discovery thread)
  std::uint64_t table_generation_seen = ~0ull;  // of the table last taken (with its writer)
  std::int64_t table_writer_seen = 0;
  std::uint32_t vehicle_changes_seen = 0;       // Header::vehicle_changes when it was read
  bool table_recheck = false;                   // our topics changed: records skipped may concern us
  Clock::time_point table_current_at = started;  // when a current, trusted table was last read
  Clock::time_point table_checked{};             // when the table was last opened
  bool table_seen_current = false;               // what that look found

  // Whether `f` may be followed: a table of this host, written by a live participant of this
  // registry whose slot names the file's owner. (A local process of the same uid as a
  // participant could write a false table; it could as well write that participant's state
  // file: trust on one host stops at the uid.)
  bool trusted(const table::File& f) const {
    const auto& h = f.header();
    if (h.host_id != own_host || h.writer == 0) return false;
    const auto* writer = slot_of(h.writer);
    return writer && reg::state_of(writer->state.load(std::memory_order_acquire)) == reg::kLive &&
           writer->uid.load(std::memory_order_relaxed) == f.owner();
  }

  // Takes the vehicle table into the table of remote participants and tells on_change what
  // changed, in one pass under the delivery lock: hosts gone or restarted lose their members;
  // of a host whose listed records changed, the records of ours, of a topic of ours, or of a
  // reader of every topic are read (`all`: every record: a new speaker), the others skipped
  // (counted; read once our topics meet theirs: table_recheck). A record must decode, be of its
  // host, id and revision, and not name a participant of this host. Returns whether the table
  // is current. Discovery thread, no lock held.
  bool follow_table(bool all) {
    bool refused = false;
    auto file = table::File::open(reg->table_path_for(group_hash), &refused);
    table_checked = Clock::now();
    if (!file || !trusted(*file)) {
      table_seen_current = false;
      if (!file && !refused) return false;  // none (yet)
      std::lock_guard lock(mutex);
      ++counters.tables_refused;
      return false;
    }
    const auto& hd = file->header();
    const bool current = table_current(hd.written_ns);
    table_seen_current = current;
    if (current) table_current_at = Clock::now();
    if (!all && !table_recheck && hd.generation == table_generation_seen && hd.writer == table_writer_seen)
      return current;
    const bool recheck = all || table_recheck;
    table_recheck = false;
    std::uint64_t taken = 0, skipped = 0, malformed_records = 0;
    std::vector<std::pair<Change, Participant>> out;
    std::unique_lock order(deliver_mutex);
    auto forget = [&](const std::vector<std::int64_t>& ids) {  // under mutex
      for (auto id : ids) {
        auto it = peers.find(id);
        if (it == peers.end() || it->second.host == 0) continue;
        table_bytes -= it->second.bytes;
        out.emplace_back(Change::left, std::move(it->second.p));
        peers.erase(it);
      }
    };
    std::set<std::int64_t> in_table;
    for (const auto& th : file->hosts()) {
      if (th.host_id == 0 || static_cast<std::uint64_t>(th.host_id) == own_host) continue;
      in_table.insert(th.host_id);
      {
        std::lock_guard lock(mutex);
        auto& host = hosts[th.host_id];
        if (host.registry_id != 0 && host.registry_id != th.registry_id) {  // restarted: its old members are gone
          std::vector<std::int64_t> gone;
          for (const auto& [id, rev] : host.members) gone.push_back(id);
          host.members.clear();
          host.listed_digest = 0;
          forget(gone);
        }
        host.registry_id = th.registry_id;
        host.speaker = th.speaker;
        host.lease = lease_of(th.lease_ms);
        host.digest = th.digest;
        if (host.last_heard == Clock::time_point{}) host.last_heard = Clock::now();
        bound[th.host_id] = th.address;  // (what its speaker bound: used if this one ever listens)
        if (!recheck && host.listed_digest == th.listed_digest && th.listed_digest != 0) continue;
      }
      const auto records = file->records(th);
      if (!records) {
        ++malformed_records;
        continue;
      }
      std::map<std::int64_t, std::int64_t> listed;
      for (const auto& r : *records) {
        listed[r.participant_id] = r.revision;
        bool held = false;
        {
          std::lock_guard lock(mutex);
          const auto p = peers.find(r.participant_id);
          if (p != peers.end() && p->second.host != th.host_id) continue;  // another host's: not ours to judge
          if (p != peers.end() && p->second.p.beacon.revision == r.revision) continue;  // held as it is
          held = p != peers.end();
        }
        if (!all && !held && !concerns(r)) {
          ++skipped;
          continue;
        }
        if (!held && of_this_host(r.participant_id)) {  // ours is known through the registry, never from a table
          ++malformed_records;
          continue;
        }
        auto bytes = file->bytes(r);
        auto b = bytes ? decode_beacon(*bytes) : std::nullopt;
        if (!b || b->participant_id != r.participant_id || b->host_id != th.host_id || b->revision != r.revision ||
            (b->flags & (beacon_t::FLAG_GOODBYE | beacon_t::FLAG_OBSERVER | beacon_t::FLAG_QUERY))) {
          ++malformed_records;
          continue;
        }
        if (auto told = apply_record(std::move(*b), bytes->size())) {
          ++taken;
          out.push_back(std::move(*told));
        }
      }
      std::lock_guard lock(mutex);
      auto& host = hosts[th.host_id];
      std::vector<std::int64_t> gone;
      for (const auto& [id, p] : peers)
        if (p.host == th.host_id && !listed.count(id)) gone.push_back(id);
      forget(gone);
      host.members = std::move(listed);
      host.listed_digest = th.listed_digest;
    }
    {
      std::lock_guard lock(mutex);
      std::vector<std::int64_t> gone;
      for (const auto& [id, p] : peers)
        if (p.host != 0 && !in_table.count(p.host)) gone.push_back(id);
      forget(gone);
      std::erase_if(hosts, [&](const auto& kv) { return !in_table.count(kv.first); });
      std::erase_if(heard, [&](const auto& kv) { return !in_table.count(kv.first); });
      counters.table_reads += 1;
      counters.table_records += taken;
      counters.table_skipped += skipped;
      counters.malformed += malformed_records;
      if (malformed_records > 0)
        warn_limited(last_malformed_log, "lcmx discovery: ignored {} malformed record(s) of the vehicle table {}",
                     malformed_records, reg->table_path_for(group_hash));
    }
    for (auto& [c, p] : out) tell(c, std::move(p));
    // What its writer had heard of the whole vehicle, we hold now (what concerns us of it).
    if ((hd.flags & table::kComplete) && follower()) complete = true;
    table_generation_seen = hd.generation;
    table_writer_seen = hd.writer;
    return current;
  }

  // A follower without a current table for kFallbackAfter acting periods listens to the group
  // itself (its speaker cannot write the table: a full /dev/shm; or it is stopped and another
  // acts), and follows again as soon as one is current. Discovery thread.
  void check_fallback() {
    if (!follows_table() || is_speaker) return;
    // In: no current table for kFallbackAfter acting periods. Out: the last look found one current.
    const bool stale = listening_fallback ? !table_seen_current
                                          : Clock::now() - table_current_at >= kFallbackAfter * act_after();
    if (stale == listening_fallback.load()) return;
    listening_fallback = stale;
    if (stale) {
      spdlog::warn("lcmx discovery: no current vehicle table {} for {} ms: participant {} listens to the vehicle "
                   "group itself until its host's speaker writes one again",
                   reg->table_path_for(group_hash),
                   std::chrono::duration_cast<std::chrono::milliseconds>(Clock::now() - table_current_at).count(),
                   self_id.load());
      std::lock_guard lock(mutex);
      for (auto& [id, h] : hosts) h.last_heard = Clock::now();  // their heartbeats reach us from now on
    } else {
      spdlog::info("lcmx discovery: participant {} follows the vehicle table {} again", self_id.load(),
                   reg->table_path_for(group_hash));
      table_generation_seen = ~0ull;
      std::lock_guard lock(mutex);
      requests.clear();
    }
    note_listening();
  }

  // A participant listening in a follower's stead: notes when the table is current again.
  void watch_table() {
    if (table_is_current()) table_current_at = Clock::now();
  }
  bool table_is_current() {
    auto file = table::File::open(reg->table_path_for(group_hash));
    table_checked = Clock::now();
    table_seen_current = file && trusted(*file) && table_current(file->header().written_ns);
    return table_seen_current;
  }

  // Under mutex: this receiver (a speaker, or a participant listening to the group) lacks
  // records of host `h` (`want`: those; empty: it needs the host's index). The caller wakes the
  // discovery thread.
  void lack(std::int64_t h, std::vector<std::pair<std::int64_t, std::int64_t>> want) {
    requests.push_back({h, std::move(want), request_due()});
  }

  // ------------------------------------------------------------ the thread
  void run() {
    auto next_periodic = Clock::now();
    while (!stopping.load()) {
      auto now = Clock::now();
      const bool periodic = now >= next_periodic;
      if (want_announce.exchange(false) || periodic) {
        publish_local(periodic);
        if (periodic) {
          next_periodic = now + options.period;
          if (options.observer && !reg && ++observer_periods % 2 == 0) want_query = true;  // other hosts' statistics
          if (options.observer && reg)  // keep the participants' statistics fresh while we watch
            reg->header->observed_until_ns.store(
                reg::now_ns() + 3 * std::chrono::duration_cast<std::chrono::nanoseconds>(options.period).count(),
                std::memory_order_relaxed);
          try_speak();
          full_due = true;  // leases are judged every period
        }
      }
      if (is_deputy) try_speak();
      try_act();
      check_acting();
      if (follows_table() && !is_speaker) {
        // A follower reads the table when it changed, when our topics did, and once per period
        // (is it still current?); a participant listening in its stead only watches for its return.
        const auto changes = reg->header->vehicle_changes.load(std::memory_order_acquire);  // pairs with write_table
        if (changes != vehicle_changes_seen || table_recheck || Clock::now() - table_checked >= options.period) {
          vehicle_changes_seen = changes;
          if (follower()) follow_table(false);
          else watch_table();
          check_fallback();
        }
      }
      if (want_query.exchange(false)) {
        send_query();
        full_due = true;
      }
      const bool reads = reg && (host_scope || is_speaker);
      if (reads) {
        // A pass: every period (full), for a change (in bursts, next_pass_at), or to retry a
        // slot read half-written (one kCoalesce after the last pass: a retry is no change).
        const auto now = Clock::now();
        const bool changed = recheck_skipped || changed_since_pass();
        const bool for_change = changed && now >= next_pass_at();
        if (full_due || for_change || (retry_soon && now - last_pass >= kCoalesce)) {
          if (for_change && !full_due) {
            pass_ring[pass_ring_next] = now;
            pass_ring_next = (pass_ring_next + 1) % kPassBurst;
          }
          retry_soon = false;
          registry_pass();
        }
      }
      if (is_speaker) speaker_duties();
      write_table();
      const bool listens = listening();
      const auto next_request = listens ? send_requests() : Clock::time_point::max();
      if (listens) expire_hosts();
      check_complete();
      const bool completing = listens && !complete.load(std::memory_order_relaxed);

      // Sleep until the next period, a host's lease, a request's time, a change of the
      // registry (or of the vehicle table), or a wake-up.
      auto until = std::min({next_periodic, listens ? next_host_expiry() : Clock::time_point::max(), next_request});
      if (completing) until = std::min(until, std::max(complete_due(), Clock::now() + kSpeakerTick));
      if (retry_soon) until = std::min(until, last_pass + kCoalesce);
      // A change waits for its pass no longer than the coalescing says (the speaker too).
      if (reads && changed_since_pass()) until = std::min(until, next_pass_at());
      if (is_speaker) until = std::min({until, Clock::now() + kSpeakerTick, flush_at});
      if (is_deputy) until = std::min(until, Clock::now() + kSpeakerTick);
      if (follows_table() && !is_speaker) {  // try_act and check_fallback when they are due
        std::lock_guard lock(mutex);
        const auto act_at = (listening_fallback ? own_heard : table_current_at) + act_after();
        const auto fallback_at = table_current_at + kFallbackAfter * act_after();
        for (auto at : {act_at, fallback_at})
          if (at > Clock::now()) until = std::min(until, at);
      }
      const auto wait = std::chrono::ceil<std::chrono::milliseconds>(until - Clock::now());
      const auto ms = std::clamp<std::int64_t>(wait.count(), 0, 1000);
      // A wake-up that came while this pass ran (announce_now() or query() after the flags
      // were read above: a publisher made while our first beacon was being built) is served
      // now, not at the next period. wake() sets the flag before it bumps wake_word: loaded
      // first, a wake-up after the check changes the word we wait on.
      const auto expected_wake = wake_word.load(std::memory_order_acquire);
      if (want_announce.load() || want_query.load()) continue;
      if (is_speaker && reads && !changed_since_pass()) {
        // The speaker also wakes on a change of the registry (a participant's new state), not
        // only at its next tick: its records then go out at once (schedule_flush).
        std::uint64_t v;
        [[maybe_unused]] auto n = ::read(wake_fd, &v, sizeof v);  // keep the eventfd from filling
        shm::WaitToken t[2] = {{&wake_word, expected_wake, true}, {&reg->header->changes, seen_changes, false}};
        if (!changed_since_pass()) shm::wait_any(std::span(t), std::chrono::milliseconds(ms));
      } else if (follower()) {
        // A follower wakes on a new vehicle table (or a wake-up of its own).
        std::uint64_t v;
        [[maybe_unused]] auto n = ::read(wake_fd, &v, sizeof v);  // keep the eventfd from filling
        shm::WaitToken t[2] = {{&wake_word, expected_wake, true}, {&reg->header->vehicle_changes, vehicle_changes_seen, false}};
        shm::wait_any(std::span(t), std::chrono::milliseconds(ms));
      } else if (is_speaker || !reads) {
        pollfd fds[1] = {{wake_fd, POLLIN, 0}};
        const int r = ::poll(fds, 1, static_cast<int>(ms));
        if (r > 0 && (fds[0].revents & POLLIN)) {
          std::uint64_t v;
          [[maybe_unused]] auto n = ::read(wake_fd, &v, sizeof v);
        }
      } else {
        // Coalesce: no pass is due yet -> wait for wake-ups only until then.
        const auto left = next_pass_at() - Clock::now();
        if (left > Clock::duration::zero()) {
          const auto rest = std::min<std::int64_t>(ms, std::chrono::duration_cast<std::chrono::milliseconds>(left).count() + 1);
          shm::WaitToken t{&wake_word, expected_wake, true};
          shm::wait_any(std::span(&t, 1), std::chrono::milliseconds(rest));
          if (changed_since_pass()) continue;  // else: nothing changed meanwhile, sleep for real below
        }
        std::vector<shm::WaitToken> t;
        t.push_back({&wake_word, expected_wake, true});
        if (sleep_on_buckets()) t.insert(t.end(), bucket_tokens.begin(), bucket_tokens.end());
        else t.push_back({&reg->header->changes, seen_changes, false});
        std::uint64_t v;
        [[maybe_unused]] auto n = ::read(wake_fd, &v, sizeof v);  // keep the eventfd from filling
        shm::wait_any(std::span(t), std::chrono::milliseconds(ms));
      }
    }
    if (is_speaker && host_scope) reg->header->speaker.store(0, std::memory_order_relaxed);
    if (is_speaker) reg->unlock(acting ? acting_byte : speaker_byte);
    if (is_deputy) reg->unlock(reg::kLockDeputy);
    acting = false;
    is_speaker = false;
    is_deputy = false;
  }

  // A change since our last pass that may concern us.
  bool changed_since_pass() const {
    if (!sleep_on_buckets()) return reg->header->changes.load(std::memory_order_acquire) != seen_changes;
    for (const auto& t : bucket_tokens)
      if (t.word->load(std::memory_order_acquire) != t.expected) return true;
    return false;
  }

  void rx_loop() {
    while (!stopping.load()) {
      pollfd fds[2] = {{wake_fd, POLLIN, 0}, {group->fd(), POLLIN, 0}};
      if (::poll(fds, 2, 200) <= 0) continue;
      if (fds[1].revents & POLLIN) drain_queued();
    }
  }
};

Discovery::Discovery(Options options, LocalFn local, ChangeFn on_change)
    : impl_(std::make_unique<Impl>(std::move(options), std::move(local), std::move(on_change))) {
  if (impl_->options.observer) {
    impl_->self_id = static_cast<std::int64_t>(random_participant_id());
    impl_->want_query = true;
  }
  // A vehicle participant follows its host's vehicle table from the start (before anything is
  // read from the group: the runtime's front door starts later).
  if (impl_->follows_table()) {
    impl_->vehicle_changes_seen = impl_->reg->header->vehicle_changes.load(std::memory_order_acquire);
    impl_->follow_table(false);
    impl_->note_listening();
  }
  impl_->thread = std::thread([this] { impl_->run(); });
  if (impl_->receive) impl_->rx_thread = std::thread([this] { impl_->rx_loop(); });
}

Discovery::~Discovery() { stop(); }

void Discovery::announce_now() {
  impl_->want_announce = true;
  impl_->wake();
}

void Discovery::query() {
  impl_->want_query = true;
  impl_->wake();
}

void Discovery::deliver(const udpm::Message& message) { impl_->on_datagram(message); }

void Discovery::stop() {
  if (!impl_ || !impl_->thread.joinable()) return;
  impl_->stopping = true;
  impl_->wake();
  impl_->thread.join();
  if (impl_->rx_thread.joinable()) impl_->rx_thread.join();
  if (impl_->joined_registry) {
    impl_->reg->leave();
    impl_->joined_registry = false;
  }
}

std::vector<Participant> Discovery::participants() const {
  std::lock_guard lock(impl_->mutex);
  std::vector<Participant> out;
  out.reserve(impl_->peers.size());
  for (const auto& [id, p] : impl_->peers) out.push_back(p.p);
  return out;
}

Counters Discovery::counters() const {
  std::lock_guard lock(impl_->mutex);
  return impl_->counters;
}

bool Discovery::speaking() const { return impl_->is_speaker.load(); }
bool Discovery::listening() const { return impl_->listening(); }
bool Discovery::complete() const { return impl_->complete.load(std::memory_order_acquire); }
std::shared_ptr<Registry> Discovery::registry() const { return impl_->registry; }
const Options& Discovery::options() const { return impl_->options; }

}  // namespace lcmx::discovery
