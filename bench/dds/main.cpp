// Roles of the DDS gateway benchmark (bench/dds/run.py starts them; docs/dds.md "Benchmark"):
//   lcmx_bench_dds sink TOPIC[,TOPIC..] COUNT  DDS reader of lcmx::dds::Envelope on each topic:
//                                              one-way latency of each sample from the timestamp in
//                                              its payload, then per topic, in the order given,
//                                              "result i=.. n=.. p50_us=.. p99_us=.. mbps=.. lost=.."
//                                              (stops 3 s after the last sample if fewer came)
//   lcmx_bench_dds dds-source TOPIC COUNT SIZE HZ   DDS writer of envelopes (HZ 0: as fast as it can)
//   lcmx_bench_dds lcmx-source CHANNEL COUNT SIZE HZ  lcmx raw publisher (the gateway exports it)
//   lcmx_bench_dds both-source CHANNEL TOPIC COUNT SIZE HZ  both in one process, interleaved: the
//                                              lcmx publisher at k/HZ, the DDS writer half a period
//                                              later, COUNT messages each (run.py's default mode)
// Payload: 8 bytes of fingerprint (0x6c636d7864647362), 8 bytes CLOCK_MONOTONIC ns at send, 8
// bytes sequence, then filler. Cyclone's network: CYCLONEDDS_URI (run.py: loopback only);
// domain: BENCH_DDS_DOMAIN.
#include <dds/dds.h>

#include <time.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <iostream>
#include <string>
#include <thread>
#include <vector>

#include "harness/options.hpp"
#include "harness/stats.hpp"
#include "lcmx/core.hpp"
#include "lcmx_envelope.h"

namespace {

constexpr std::uint64_t kFingerprint = 0x6c636d7864647362ull;

std::int64_t now_ns() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

void stamp(std::vector<std::uint8_t>& p, std::uint64_t seq) {
  std::memcpy(p.data(), &kFingerprint, 8);
  const std::int64_t t = now_ns();
  std::memcpy(p.data() + 8, &t, 8);
  std::memcpy(p.data() + 16, &seq, 8);
}

dds_domainid_t domain() {
  const char* d = std::getenv("BENCH_DDS_DOMAIN");
  return d ? static_cast<dds_domainid_t>(std::atoi(d)) : 0;
}

dds_entity_t check(dds_entity_t e, const char* what) {
  if (e < 0) {
    std::fprintf(stderr, "lcmx_bench_dds: %s: %s\n", what, dds_strretcode(e));
    std::exit(1);
  }
  return e;
}

dds_qos_t* qos(bool keep_all) {
  dds_qos_t* q = dds_create_qos();
  dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_SECS(10));
  if (keep_all) dds_qset_history(q, DDS_HISTORY_KEEP_ALL, 0);
  else dds_qset_history(q, DDS_HISTORY_KEEP_LAST, 16);
  return q;
}

void pace(std::int64_t start, std::uint64_t k, double hz) {
  if (hz <= 0) return;
  const auto due = start + static_cast<std::int64_t>(static_cast<double>(k) * 1e9 / hz);
  // One absolute sleep until the due time, as a periodic driver does (a loop of short sleeps
  // kept this process waking every ~50 us, which changes where the readers' wake-ups land).
  const timespec ts{static_cast<time_t>(due / 1000000000), static_cast<long>(due % 1000000000)};
  while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr) == EINTR) {
  }
}

// One reader's samples: latencies (us), sequence bookkeeping, bytes, first send / last receipt.
struct Track {
  dds_entity_t reader = 0;
  std::vector<double> lat;
  std::uint64_t last_seq = 0, bytes = 0, lost = 0;
  long got = 0;
  std::int64_t first = 0, last = 0;  // first: the first received sample's send time
};

int sink(const std::string& topics, long count) {
  const dds_entity_t pp = check(dds_create_participant(domain(), nullptr, nullptr), "participant");
  const dds_entity_t ws = check(dds_create_waitset(pp), "waitset");
  std::vector<Track> tracks;
  for (std::size_t at = 0; at <= topics.size();) {
    const std::size_t comma = std::min(topics.find(',', at), topics.size());
    const std::string topic = topics.substr(at, comma - at);
    at = comma + 1;
    const dds_entity_t tp =
        check(dds_create_topic(pp, &lcmx_dds_Envelope_desc, topic.c_str(), nullptr, nullptr), "topic");
    dds_qos_t* q = qos(true);
    Track t;
    t.reader = check(dds_create_reader(pp, tp, q, nullptr), "reader");
    dds_delete_qos(q);
    const dds_entity_t rc = check(dds_create_readcondition(t.reader, DDS_ANY_STATE), "readcondition");
    dds_waitset_attach(ws, rc, t.reader);
    tracks.push_back(std::move(t));
  }
  std::cout << "ready" << std::endl;
  auto all_done = [&] {
    return std::all_of(tracks.begin(), tracks.end(), [&](const Track& t) { return t.got >= count; });
  };
  std::int64_t last_any = 0;
  const std::int64_t deadline = now_ns() + 120'000'000'000ll;
  // Until `count` samples on every topic, or 3 s without one after the first (the rest was
  // lost upstream).
  while (!all_done() && now_ns() < deadline && !(last_any > 0 && now_ns() - last_any > 3'000'000'000ll)) {
    dds_waitset_wait(ws, nullptr, 0, DDS_MSECS(200));
    for (auto& tr : tracks) {
      void* samples[16] = {};
      dds_sample_info_t infos[16];
      int n;
      while ((n = dds_take(tr.reader, samples, infos, 16, 16)) > 0) {
        const std::int64_t t = now_ns();
        for (int i = 0; i < n; ++i) {
          if (!infos[i].valid_data) continue;
          const auto* e = static_cast<const lcmx_dds_Envelope*>(samples[i]);
          if (e->payload._length < 24) continue;
          std::int64_t sent;
          std::uint64_t seq;
          std::memcpy(&sent, e->payload._buffer + 8, 8);
          std::memcpy(&seq, e->payload._buffer + 16, 8);
          if (tr.got > 0 && seq > tr.last_seq + 1) tr.lost += seq - tr.last_seq - 1;
          tr.last_seq = seq;
          if (tr.got == 0) tr.first = sent;
          tr.last = last_any = t;
          tr.bytes += e->payload._length;
          tr.lat.push_back(static_cast<double>(t - sent) / 1000.0);
          ++tr.got;
        }
        dds_return_loan(tr.reader, samples, n);
        samples[0] = nullptr;
      }
    }
  }
  for (std::size_t i = 0; i < tracks.size(); ++i) {
    const Track& tr = tracks[i];
    // Latency: without the first 10% (discovery, first allocations).
    const auto st = lcmxbench::stats_of({tr.lat.begin() + static_cast<long>(tr.lat.size() / 10), tr.lat.end()});
    const double secs = static_cast<double>(tr.last - tr.first) / 1e9;
    std::printf("result i=%zu n=%ld p50_us=%.1f p99_us=%.1f mbps=%.1f lost=%llu\n", i, tr.got, st.p50, st.p99,
                secs > 0 ? static_cast<double>(tr.bytes) * 8 / 1e6 / secs : 0.0,
                static_cast<unsigned long long>(tr.lost));
  }
  std::fflush(stdout);
  dds_delete(pp);
  return all_done() ? 0 : 1;
}

// A DDS writer of envelopes on `topic` (reliable KEEP_LAST 16: the gateway's writer's defaults),
// matched with a reader before it returns; exits the process if none comes within 30 s.
struct DdsWriter {
  dds_entity_t participant = 0, writer = 0;
  explicit DdsWriter(const std::string& topic) {
    participant = check(dds_create_participant(domain(), nullptr, nullptr), "participant");
    const dds_entity_t tp =
        check(dds_create_topic(participant, &lcmx_dds_Envelope_desc, topic.c_str(), nullptr, nullptr), "topic");
    dds_qos_t* q = qos(false);
    writer = check(dds_create_writer(participant, tp, q, nullptr), "writer");
    dds_delete_qos(q);
    dds_set_status_mask(writer, DDS_PUBLICATION_MATCHED_STATUS);
    const std::int64_t deadline = now_ns() + 30'000'000'000ll;
    for (;;) {
      dds_publication_matched_status_t st{};
      dds_get_publication_matched_status(writer, &st);
      if (st.current_count > 0) break;
      if (now_ns() > deadline) {
        std::fprintf(stderr, "lcmx_bench_dds: no reader of %s within 30 s\n", topic.c_str());
        std::exit(1);
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(5));  // polling discovery, no data yet
    }
  }
  DdsWriter(const DdsWriter&) = delete;
  DdsWriter& operator=(const DdsWriter&) = delete;
  ~DdsWriter() {
    dds_wait_for_acks(writer, DDS_SECS(30));
    dds_delete(participant);
  }
  void write(std::vector<std::uint8_t>& p) {
    lcmx_dds_Envelope e{};
    e.channel = const_cast<char*>("BENCH");
    e.type_name = const_cast<char*>("");
    e.payload._buffer = p.data();
    e.payload._length = e.payload._maximum = static_cast<std::uint32_t>(p.size());
    dds_write(writer, &e);
  }
};

int dds_source(const std::string& topic, long count, std::size_t size, double hz) {
  std::vector<std::uint8_t> p(std::max<std::size_t>(size, 24), 0x5a);
  {
    DdsWriter w(topic);
    const std::int64_t start = now_ns();
    for (long k = 0; k < count; ++k) {
      pace(start, static_cast<std::uint64_t>(k), hz);
      stamp(p, static_cast<std::uint64_t>(k));
      w.write(p);
    }
  }  // waits for the acknowledgements
  std::cout << "sent " << count << std::endl;
  return 0;
}

// An lcmx raw publisher of `channel` (the gateway exports it), subscribed by the gateway before
// it returns; exits the process if the gateway does not subscribe within 30 s.
struct LcmxPublisher {
  lcmx::Runtime rt = lcmx::Runtime::create();
  lcmx::Node node = rt.create_node("bench_dds_source");
  lcmx::RawPublisher pub;
  explicit LcmxPublisher(const std::string& channel) : pub(node.advertise_raw(channel)) {
    if (!pub.wait_for_subscribers(1, std::chrono::seconds(30))) {
      std::fprintf(stderr, "lcmx_bench_dds: the gateway did not subscribe to %s within 30 s\n", channel.c_str());
      std::exit(1);
    }
  }
  void publish(const std::vector<std::uint8_t>& p) { pub.publish(std::as_bytes(std::span(p))); }
};

// Says "sent COUNT", then keeps the lcmx publisher until the driver closes stdin (the gateway
// drains meanwhile).
int sent_then_wait(long count) {
  std::cout << "sent " << count << std::endl;
  std::string line;
  std::getline(std::cin, line);
  return 0;
}

int lcmx_source(const std::string& channel, long count, std::size_t size, double hz) {
  LcmxPublisher lx(channel);
  std::vector<std::uint8_t> p(std::max<std::size_t>(size, 24), 0x5a);
  const std::int64_t start = now_ns();
  for (long k = 0; k < count; ++k) {
    pace(start, static_cast<std::uint64_t>(k), hz);
    stamp(p, static_cast<std::uint64_t>(k));
    lx.publish(p);
  }
  return sent_then_wait(count);
}

// Both paths from one process, interleaved: the k-th lcmx message at k/hz, the k-th DDS sample
// half a period later, so that the machine's drift falls on both paths alike.
int both_source(const std::string& channel, const std::string& topic, long count, std::size_t size, double hz) {
  LcmxPublisher lx(channel);
  std::vector<std::uint8_t> p(std::max<std::size_t>(size, 24), 0x5a);
  {
    DdsWriter w(topic);
    const std::int64_t start = now_ns();
    for (long k = 0; k < count; ++k) {
      pace(start, 2 * static_cast<std::uint64_t>(k), 2 * hz);
      stamp(p, static_cast<std::uint64_t>(k));
      lx.publish(p);
      pace(start, 2 * static_cast<std::uint64_t>(k) + 1, 2 * hz);
      stamp(p, static_cast<std::uint64_t>(k));
      w.write(p);
    }
  }  // waits for the acknowledgements
  return sent_then_wait(count);
}

}  // namespace

const char* const kUsage =
    "usage: lcmx_bench_dds sink TOPIC[,TOPIC..] COUNT | dds-source TOPIC COUNT SIZE HZ |\n"
    "       lcmx-source CHANNEL COUNT SIZE HZ | both-source CHANNEL TOPIC COUNT SIZE HZ\n"
    "The roles of bench/dds/run.py (docs/dds.md \"Benchmark\").\n";

int main(int argc, char** argv) {
  if (lcmxbench::help_asked(argc, argv)) return lcmxbench::usage(kUsage, true);
  const std::string role = argc > 1 ? argv[1] : "";
  if (role == "sink" && argc == 4) return sink(argv[2], std::atol(argv[3]));
  if (role == "dds-source" && argc == 6)
    return dds_source(argv[2], std::atol(argv[3]), static_cast<std::size_t>(std::atol(argv[4])), std::atof(argv[5]));
  if (role == "lcmx-source" && argc == 6)
    return lcmx_source(argv[2], std::atol(argv[3]), static_cast<std::size_t>(std::atol(argv[4])), std::atof(argv[5]));
  if (role == "both-source" && argc == 7)
    return both_source(argv[2], argv[3], std::atol(argv[4]), static_cast<std::size_t>(std::atol(argv[5])),
                       std::atof(argv[6]));
  return lcmxbench::usage(kUsage, false);
}
