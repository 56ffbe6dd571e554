// Multi-process integration tests: every test starts real lcmx_test_peer processes, on real
// shared memory and a real discovery group of its own (Session), with a watchdog.
#include <algorithm>

#include "lcmx/core.hpp"
#include "lcmx_examples/pose_t.hpp"
#include "support.hpp"

using namespace lcmx::it;

namespace {

std::string sources(const Summary& s) { return s.str("sources"); }

}  // namespace

TEST_CASE("late subscriber: starts after the publisher and receives from then on", "[integration]") {
  Session s(1);
  const auto ch = unique_channel("LATE_SUB", 1);
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "pose", "--count", "0", "--rate", "200",
                      "--shm-slots", "256", "--id", "A"});
  REQUIRE(pub.expect("READY"));
  REQUIRE(wait_until([&] { return published(pub) >= 50; }, 10000ms, 20ms));
  const long long before = published(pub);

  auto& sub = s.peer({"sub", "--channel", ch, "--type", "pose", "--publishers", "1"});
  REQUIRE(sub.expect("READY"));
  REQUIRE(sub.expect("MATCHED"));
  auto st = poll_sub(sub, ch, [](const Summary& x) { return x.num("received") >= 100; }, 15000ms);
  REQUIRE(st);
  const auto fin = of(sub.summaries("quit"), ch);
  CHECK(sub.wait() == 0);
  INFO(sub.output());
  CHECK(fin.num("first") >= before);  // nothing from before it subscribed
  CHECK(fin.num("received") >= 100);
  CHECK(fin.num("duplicates") == 0);
  CHECK(fin.num("out_of_order") == 0);
  CHECK(fin.num("gaps") == 0);  // from then on: every message
  CHECK(fin.num("drops") == 0);
  CHECK(fin.num("bad_content") == 0);
  CHECK(fin.str("paths") == "shm");
}

TEST_CASE("late publisher: a subscriber waiting first gets every message", "[integration]") {
  Session s(2);
  const auto ch = unique_channel("LATE_PUB", 2);
  auto& sub = s.peer({"sub", "--channel", ch, "--type", "pose"});
  REQUIRE(sub.expect("READY"));
  // The ring holds every message: none can be lost however late the subscriber is scheduled.
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "pose", "--count", "300", "--rate", "1000",
                      "--subscribers", "1", "--shm-slots", "512", "--hold", "--id", "A"});
  REQUIRE(pub.expect("MATCHED"));
  REQUIRE(pub.expect("PUBLISHED"));
  CHECK(poll_sub(sub, ch, [](const Summary& x) { return x.num("received") + x.num("drops") >= 300; }, 10000ms));
  const auto fin = of(sub.summaries("quit"), ch);
  CHECK(sub.wait() == 0);
  pub.send("quit");
  CHECK(pub.wait() == 0);
  INFO(sub.output());
  CHECK(fin.num("received") == 300);
  CHECK(fin.num("drops") == 0);
  CHECK(fin.num("first") == 0);
  CHECK(fin.num("last") == 299);
  CHECK(fin.num("duplicates") == 0);
  CHECK(fin.num("out_of_order") == 0);
  CHECK(fin.num("gaps") == 0);
  CHECK(fin.num("bad_content") == 0);
  CHECK(fin.str("paths") == "shm");
}

TEST_CASE("publisher killed -9: subscribers live on - segment reclaimed - unmatched when its process exits",
          "[integration]") {
  Session s(3);
  const auto a = unique_channel("KILLPUB_A", 3);
  const auto b = unique_channel("KILLPUB_B", 3);
  auto& sub = s.peer({"sub", "--channel", a, "--channel", b, "--type", "pose", "--publishers", "1"});
  REQUIRE(sub.expect("READY"));
  auto& pa = s.peer({"pub", "--channel", a, "--type", "pose", "--count", "0", "--rate", "200", "--shm-slots", "256", "--id", "A"});
  auto& pb = s.peer({"pub", "--channel", b, "--type", "pose", "--count", "0", "--rate", "200", "--shm-slots", "256", "--id", "B"});
  REQUIRE(pa.expect("READY"));
  REQUIRE(pb.expect("READY"));
  REQUIRE(sub.expect("MATCHED"));
  REQUIRE(poll_sub(sub, a, [](const Summary& x) { return x.num("received") >= 20; }, 10000ms));

  const pid_t dead = pa.pid();
  const auto segments = shm_segments_of(dead);
  REQUIRE(!segments.empty());
  pa.kill9();
  const auto killed_at = Clock::now();

  // The subscriber process keeps running and still receives the other publisher.
  const long long b0 = of(sub.summaries("status"), b).num("received");
  REQUIRE(poll_sub(sub, b, [&](const Summary& x) { return x.num("received") >= b0 + 40; }, 10000ms));

  // Unmatched: no goodbye was sent, but its process exit is seen (pidfd; the lease would do
  // it too, lifecycle_test.cpp checks it is the exit).
  REQUIRE(sub.wait_seen("EVENT publisher_unmatched " + a, 5000ms));
  INFO("unmatched " << std::chrono::duration_cast<ms>(Clock::now() - killed_at).count() << " ms after the kill");
  const auto st = of(sub.summaries("status"), a);
  CHECK(st.num("publishers") == 0);
  CHECK(st.num("duplicates") == 0);
  CHECK(st.num("bad_content") == 0);

  // A new Runtime (another process) reclaims the dead publisher's segment.
  auto& fresh = s.peer({"idle", "--node", "fresh"});
  REQUIRE(fresh.expect("READY"));
  for (const auto& seg : segments) CHECK_FALSE(shm_exists(seg));
  // ... and the live publisher's segment stays.
  CHECK_FALSE(shm_segments_of(pb.pid()).empty());
  // Still delivering after all that.
  const long long b1 = of(sub.summaries("status"), b).num("received");
  REQUIRE(poll_sub(sub, b, [&](const Summary& x) { return x.num("received") >= b1 + 20; }, 10000ms));
  const auto fin = of(sub.summaries("quit"), b);
  CHECK(sub.wait() == 0);
  CHECK(fin.num("gaps") == 0);
  CHECK(fin.num("duplicates") == 0);
}

TEST_CASE("publisher killed -9: its segment is reclaimed after the lease with no new Runtime",
          "[integration]") {
  // DESIGN.md "Leases": a participant declared gone after its lease has its shared memory
  // reclaimed. Here the only other participant (the subscriber) sees the lease expire.
  Session s(4);
  const auto a = unique_channel("LEASE_RECLAIM", 4);
  auto& sub = s.peer({"sub", "--channel", a, "--type", "pose", "--publishers", "1"});
  REQUIRE(sub.expect("READY"));
  auto& pa = s.peer({"pub", "--channel", a, "--type", "pose", "--count", "0", "--rate", "100"});
  REQUIRE(sub.expect("MATCHED"));
  const auto segments = shm_segments_of(pa.pid());
  REQUIRE(!segments.empty());
  pa.kill9();
  REQUIRE(sub.wait_seen("EVENT participant_left", 5000ms));
  const bool gone = wait_until(
      [&] { return std::none_of(segments.begin(), segments.end(), [](const auto& n) { return shm_exists(n); }); },
      s.lease_ms * 3);
  INFO("segment " << segments.front() << " of the dead publisher still in /dev/shm " << 3 * s.lease_ms.count()
                  << " ms after its lease expired");
  CHECK(gone);
}

TEST_CASE("subscriber killed -9: the publisher keeps its rate and the other subscriber is unaffected",
          "[integration]") {
  Session s(5);
  const auto ch = unique_channel("KILLSUB", 5);
  auto& s1 = s.peer({"sub", "--channel", ch, "--type", "bench", "--publishers", "1", "--node", "victim"});
  auto& s2 = s.peer({"sub", "--channel", ch, "--type", "bench", "--publishers", "1", "--node", "survivor"});
  REQUIRE(s1.expect("READY"));
  REQUIRE(s2.expect("READY"));
  const double rate = 1000;
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "bench", "--size", "512", "--count", "0", "--rate", "1000",
                      "--subscribers", "2", "--shm-slots", "128", "--id", "A"});
  REQUIRE(pub.expect("MATCHED"));
  REQUIRE(poll_sub(s2, ch, [](const Summary& x) { return x.num("received") >= 200; }, 10000ms));
  REQUIRE(poll_sub(s1, ch, [](const Summary& x) { return x.num("received") >= 200; }, 10000ms));

  s1.kill9();
  const auto t0 = Clock::now();
  const long long p0 = published(pub);
  const long long r0 = of(s2.summaries("status"), ch).num("received");
  REQUIRE(poll_sub(s2, ch, [&](const Summary& x) { return x.num("received") >= r0 + 1000; }, 10000ms));
  const long long p1 = published(pub);
  const double secs = std::chrono::duration<double>(Clock::now() - t0).count();
  const double measured = static_cast<double>(p1 - p0) / secs;
  INFO("publisher rate after the kill: " << measured << " Hz (configured " << rate << ")");
  CHECK(measured >= 0.7 * rate);

  // The publisher learns that the subscriber's participant is gone (lease).
  CHECK(pub.wait_seen("EVENT participant_left", 5000ms));
  const auto fin = of(s2.summaries("quit"), ch);
  CHECK(s2.wait() == 0);
  INFO(s2.output());
  CHECK(fin.num("duplicates") == 0);
  CHECK(fin.num("out_of_order") == 0);
  CHECK(fin.num("gaps") == 0);
  CHECK(fin.num("drops") == 0);
  CHECK(fin.num("bad_content") == 0);
  CHECK(fin.num("decode_errors") == 0);
  pub.send("quit");
  CHECK(pub.wait() == 0);
}

TEST_CASE("6 MB images (1920x1080x3) across processes at 10 Hz: all delivered with content intact",
          "[integration]") {
  Session s(6, 45000ms);
  const auto ch = unique_channel("IMAGE", 6);
  const int n = 20;
  auto& s1 = s.peer({"sub", "--channel", ch, "--type", "image", "--expect", std::to_string(n), "--node", "viewer1"});
  auto& s2 = s.peer({"sub", "--channel", ch, "--type", "image", "--expect", std::to_string(n), "--node", "viewer2"});
  REQUIRE(s1.expect("READY"));
  REQUIRE(s2.expect("READY"));
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "image", "--width", "1920", "--height", "1080", "--count",
                      std::to_string(n), "--rate", "10", "--subscribers", "2", "--hold", "--id", "cam"});
  REQUIRE(pub.expect("MATCHED"));
  REQUIRE(pub.expect("PUBLISHED", 15000ms));
  for (Child* c : {&s1, &s2}) {
    const auto fin = of(c->read_summaries(15000ms), ch);
    CHECK(c->wait() == 0);
    INFO(c->output());
    CHECK(fin.num("received") == n);
    CHECK(fin.num("first") == 0);
    CHECK(fin.num("last") == n - 1);
    CHECK(fin.num("gaps") == 0);
    CHECK(fin.num("drops") == 0);
    CHECK(fin.num("bad_content") == 0);
    CHECK(fin.num("decode_errors") == 0);
    CHECK(fin.str("paths") == "shm");
  }
  pub.send("quit");
  CHECK(pub.wait() == 0);
}

TEST_CASE("type mismatch across processes: not matched and both sides report it", "[integration]") {
  Session s(7);
  const auto ch = unique_channel("MISMATCH", 7);
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "pose", "--count", "0", "--rate", "50", "--node", "poser"});
  auto& sub = s.peer({"sub", "--channel", ch, "--type", "image", "--node", "imager"});
  REQUIRE(pub.expect("READY"));
  REQUIRE(sub.expect("READY"));
  CHECK(sub.wait_seen("EVENT type_mismatch " + ch, 5000ms));
  CHECK(pub.wait_seen("EVENT type_mismatch " + ch, 5000ms));
  REQUIRE(wait_until([&] { return published(pub) >= 20; }, 5000ms, 20ms));
  const auto st = of(sub.summaries("status"), ch);
  INFO(sub.output());
  CHECK(st.num("received") == 0);
  CHECK(st.num("publishers") == 0);
  CHECK(st.num("decode_errors") == 0);
  REQUIRE(st.num("errors") >= 1);
  REQUIRE(!st.errors.empty());
  CHECK(st.errors.front().find("type mismatch") != std::string::npos);
  CHECK(st.errors.front().find("pose_t") != std::string::npos);
  CHECK(st.errors.front().find("image_t") != std::string::npos);
#ifdef LCMX_TOOL
  const auto r = s.run({LCMX_TOOL, "--url", s.url, "topics"});
  INFO(r.out);
  CHECK(r.rc == 0);
  CHECK(r.out.find(ch) != std::string::npos);
  CHECK(r.out.find("CONFLICT") != std::string::npos);
  CHECK(r.out.find("ERROR: type mismatch") != std::string::npos);
#else
  WARN("lcmx tool not built (LCMX_BUILD_APPS=OFF): CONFLICT in `lcmx topics` not checked");
#endif
}

TEST_CASE("50 topics in one process plus a subscriber process for a few: all delivered", "[integration]") {
  Session s(8);
  constexpr int kTopics = 50, kMessages = 20;
  std::vector<std::string> channels;
  for (int i = 0; i < kTopics; ++i) channels.push_back(unique_channel("T" + std::to_string(i), 8));
  const std::vector<int> remote = {0, 17, 49};
  std::vector<std::string> args = {"sub", "--type", "pose", "--expect", std::to_string(kMessages), "--publishers", "1"};
  for (int i : remote) args.insert(args.end(), {"--channel", channels[static_cast<std::size_t>(i)]});
  auto& sub = s.peer(args);
  REQUIRE(sub.expect("READY"));

  auto rt = lcmx::Runtime::create();
  std::vector<lcmx::Node> nodes;
  for (int i = 0; i < 5; ++i) nodes.push_back(rt.create_node("n" + std::to_string(i)));
  std::vector<lcmx::Publisher<lcmx_examples::pose_t>> pubs;
  std::vector<lcmx::Subscriber<lcmx_examples::pose_t>> subs;
  std::vector<std::atomic<int>> got(kTopics);
  std::vector<std::atomic<int>> bad(kTopics);
  lcmx::PublisherOptions po;
  po.shm_slots = 64;
  lcmx::SubscriberOptions so;
  so.queue_depth = 64;
  for (int i = 0; i < kTopics; ++i) {
    auto& node = nodes[static_cast<std::size_t>(i % 5)];
    pubs.push_back(node.advertise<lcmx_examples::pose_t>(channels[static_cast<std::size_t>(i)], po));
    subs.push_back(node.subscribe<lcmx_examples::pose_t>(
        channels[static_cast<std::size_t>(i)],
        [&, i](const lcmx_examples::pose_t& m) {
          if (m.header.seq != got[static_cast<std::size_t>(i)].load() || m.header.frame_id != std::to_string(i))
            ++bad[static_cast<std::size_t>(i)];
          ++got[static_cast<std::size_t>(i)];
        },
        so));
  }
  for (int i = 0; i < kTopics; ++i) {
    const bool is_remote = std::find(remote.begin(), remote.end(), i) != remote.end();
    INFO("topic " << i);
    REQUIRE(pubs[static_cast<std::size_t>(i)].wait_for_subscribers(is_remote ? 2 : 1, 10000ms));
  }
  REQUIRE(sub.expect("MATCHED"));
  for (int k = 0; k < kMessages; ++k)
    for (int i = 0; i < kTopics; ++i) {
      lcmx_examples::pose_t m{};
      m.header.seq = k;
      m.header.frame_id = std::to_string(i);
      m.position[0] = k;
      m.orientation[3] = 1.0;
      pubs[static_cast<std::size_t>(i)].publish(m);
    }
  const bool all = wait_until(
      [&] {
        return std::all_of(got.begin(), got.end(), [](const auto& g) { return g.load() >= kMessages; });
      },
      10000ms);
  for (int i = 0; i < kTopics; ++i) {
    INFO("topic " << i);
    CHECK(got[static_cast<std::size_t>(i)].load() == kMessages);
    CHECK(bad[static_cast<std::size_t>(i)].load() == 0);
    const auto st = subs[static_cast<std::size_t>(i)].stats();
    CHECK(st.drops == 0);
    REQUIRE(st.publishers.size() == 1);
    CHECK(st.publishers[0].path == lcmx::Path::intra);
  }
  REQUIRE(all);
  const auto fin = sub.read_summaries(10000ms);
  CHECK(sub.wait() == 0);
  INFO(sub.output());
  for (int i : remote) {
    const auto st = of(fin, channels[static_cast<std::size_t>(i)]);
    CHECK(st.num("received") == kMessages);
    CHECK(st.num("gaps") == 0);
    CHECK(st.num("bad_content") == 0);
    CHECK(st.str("paths") == "shm");
  }
}

TEST_CASE("2 publishers -> 2 subscribers in 4 processes with 1000s of messages: no duplicates and ordered per publisher",
          "[integration]") {
  Session s(9);
  const auto ch = unique_channel("ORDER", 9);
  constexpr int kCount = 3000;
  auto& s1 = s.peer({"sub", "--channel", ch, "--type", "bench", "--publishers", "2", "--node", "s1"});
  auto& s2 = s.peer({"sub", "--channel", ch, "--type", "bench", "--publishers", "2", "--node", "s2"});
  REQUIRE(s1.expect("READY"));
  REQUIRE(s2.expect("READY"));
  const std::vector<std::string> common = {"--channel", ch, "--type", "bench", "--size", "256", "--count",
                                           std::to_string(kCount), "--rate", "3000", "--subscribers", "2",
                                           "--shm-slots", "256", "--hold"};
  auto pub_args = [&](const char* id) {
    std::vector<std::string> a = {"pub", "--id", id, "--node", std::string("pub_") + id};
    a.insert(a.end(), common.begin(), common.end());
    return a;
  };
  auto& pa = s.peer(pub_args("A"));
  auto& pb = s.peer(pub_args("B"));
  REQUIRE(pa.expect("MATCHED"));
  REQUIRE(pb.expect("MATCHED"));
  REQUIRE(s1.expect("MATCHED"));
  REQUIRE(s2.expect("MATCHED"));
  REQUIRE(pa.expect("PUBLISHED", 20000ms));
  REQUIRE(pb.expect("PUBLISHED", 20000ms));
  for (Child* c : {&s1, &s2}) {
    // Every message either arrived or was counted as a drop; then stop.
    auto st = poll_sub(*c, ch, [&](const Summary& x) { return x.num("received") + x.num("drops") >= 2 * kCount; },
                       10000ms);
    CHECK(st);
    const auto fin = of(c->summaries("quit"), ch);
    CHECK(c->wait() == 0);
    INFO(c->output());
    CHECK(fin.num("duplicates") == 0);
    CHECK(fin.num("out_of_order") == 0);
    CHECK(fin.num("received") + fin.num("drops") == 2 * kCount);
    CHECK(fin.num("gaps") == fin.num("drops"));
    CHECK(sources(fin).find("A:") != std::string::npos);
    CHECK(sources(fin).find("B:") != std::string::npos);
    CHECK(fin.num("publishers") == 2);
    CHECK(fin.num("bad_content") == 0);
    if (fin.num("drops") != 0) WARN("subscriber lost " << fin.num("drops") << " messages (counted as drops)");
  }
  pa.send("quit");
  pb.send("quit");
  CHECK(pa.wait() == 0);
  CHECK(pb.wait() == 0);
}

// While other lcmx processes of the host run, the registry's speaker reclaims a dead
// participant's segments by name (its death is seen at once: pidfd); the first Runtime of a
// host (the one that creates the registry) scans /dev/shm for any left before.
TEST_CASE("stale segment of a crashed process is reclaimed while another Runtime runs", "[integration]") {
  Session s(10);
  const auto ch = unique_channel("STALE", 10);
  auto& live = s.peer({"idle", "--channel", ch + "_live", "--node", "live"});
  auto& crash = s.peer({"idle", "--channel", ch, "--node", "crasher"});
  REQUIRE(live.expect("READY"));
  REQUIRE(crash.expect("READY"));
  const auto stale = shm_segments_of(crash.pid());
  const auto live_segments = shm_segments_of(live.pid());
  REQUIRE(!stale.empty());
  REQUIRE(!live_segments.empty());
  crash.kill9();  // reaped: the segment's owner is gone
  // (Any Runtime started on this host from now on may remove it: parallel tests included.)
  auto& fresh = s.peer({"idle", "--node", "fresh"});
  REQUIRE(fresh.expect("READY"));
  for (const auto& n : stale) CHECK(wait_until([&] { return !shm_exists(n); }, 5000ms, 10ms));
  for (const auto& n : live_segments) CHECK(shm_exists(n));  // a live process's segment stays
  live.send("quit");
  CHECK(live.wait() == 0);
  for (const auto& n : live_segments) CHECK_FALSE(shm_exists(n));  // removed on clean exit
}

TEST_CASE("restart: a publisher exits and a new one on the same channel is matched again", "[integration]") {
  Session s(11);
  const auto ch = unique_channel("RESTART", 11);
  auto& sub = s.peer({"sub", "--channel", ch, "--type", "pose"});
  REQUIRE(sub.expect("READY"));
  {
    auto& p1 = s.peer({"pub", "--channel", ch, "--type", "pose", "--count", "50", "--rate", "500", "--subscribers",
                       "1", "--shm-slots", "64", "--hold", "--id", "P1"});
    REQUIRE(p1.expect("PUBLISHED"));
    REQUIRE(poll_sub(sub, ch, [](const Summary& x) { return x.num("received") >= 50; }, 10000ms));
    p1.send("quit");
    CHECK(p1.wait() == 0);
  }
  // Goodbye: unmatched at once, well before the lease.
  const auto t0 = Clock::now();
  REQUIRE(sub.wait_seen("EVENT publisher_unmatched " + ch, 5000ms));
  CHECK(Clock::now() - t0 < s.lease_ms);
  auto& p2 = s.peer({"pub", "--channel", ch, "--type", "pose", "--count", "50", "--rate", "500", "--subscribers",
                     "1", "--shm-slots", "64", "--hold", "--id", "P2"});
  REQUIRE(p2.expect("MATCHED"));
  REQUIRE(p2.expect("PUBLISHED"));
  auto st = poll_sub(sub, ch, [](const Summary& x) { return x.num("received") >= 100; }, 10000ms);
  REQUIRE(st);
  const auto fin = of(sub.summaries("quit"), ch);
  CHECK(sub.wait() == 0);
  p2.send("quit");
  CHECK(p2.wait() == 0);
  INFO(sub.output());
  CHECK(fin.num("received") == 100);
  CHECK(sources(fin) == "P1:50,P2:50");
  CHECK(fin.num("publishers") == 1);
  CHECK(fin.num("duplicates") == 0);
  CHECK(fin.num("out_of_order") == 0);
  CHECK(fin.num("gaps") == 0);
}

namespace {
// One publisher process publishes `count` bench messages of `size` bytes as fast as it can
// into a ring that holds them all; returns the subscriber's final summary.
Summary burst(Session& s, const std::string& ch, int count, const std::string& size, const std::string& initial_slot,
              bool hold) {
  auto& sub = s.peer({"sub", "--channel", ch, "--type", "bench"});
  REQUIRE(sub.expect("READY"));
  std::vector<std::string> args = {"pub", "--channel", ch, "--type", "bench", "--size", size, "--count",
                                   std::to_string(count), "--rate", "0", "--subscribers", "1", "--shm-slots", "512",
                                   "--initial-slot", initial_slot, "--id", "A"};
  if (hold) args.push_back("--hold");
  auto& pub = s.peer(args);
  REQUIRE(pub.expect("PUBLISHED"));
  if (!hold) CHECK(pub.wait() == 0);  // clean exit: goodbye right after the last commit
  poll_sub(sub, ch, [&](const Summary& x) { return x.num("received") + x.num("drops") >= count; }, 3000ms);
  const auto fin = of(sub.summaries("quit"), ch);
  CHECK(sub.wait() == 0);
  if (hold) {
    pub.send("quit");
    CHECK(pub.wait() == 0);
  }
  return fin;
}
}  // namespace

TEST_CASE("a publisher that exits cleanly right after publishing: what it committed is delivered or counted",
          "[integration]") {
  // No segment growth here (first slot fits the message): only the exit is under test.
  Session s(12);
  for (int round = 0; round < 6; ++round) {
    const auto fin = burst(s, unique_channel("EXIT_TAIL_" + std::to_string(round), 12), 300, "100000", "131072", false);
    INFO("round " << round << ": received " << fin.str("received") << " last " << fin.str("last") << " drops "
                  << fin.str("drops"));
    CHECK(fin.num("duplicates") == 0);
    CHECK(fin.num("received") + fin.num("drops") == 300);
  }
}

TEST_CASE("segment growth mid-stream: messages are delivered or counted as drops - never lost silently",
          "[integration]") {
  // 100 kB messages into a ring whose first slots are 4 kB: the Writer moves to a larger
  // generation at once; the ring (512 slots) holds every message, the publisher stays alive.
  Session s(13);
  for (int round = 0; round < 6; ++round) {
    const auto fin = burst(s, unique_channel("GROWTH_" + std::to_string(round), 13), 300, "100000", "4096", true);
    INFO("round " << round << ": received " << fin.str("received") << " first_gap " << fin.str("first_gap")
                  << " gaps " << fin.str("gaps") << " drops " << fin.str("drops"));
    CHECK(fin.num("duplicates") == 0);
    CHECK(fin.num("gaps") == fin.num("drops"));
    CHECK(fin.num("received") + fin.num("drops") == 300);
  }
}

TEST_CASE("keep last N across processes (shm): late subscribers get the last N once, then every live message",
          "[integration][history]") {
  Session s(140);
  const auto ch = unique_channel("KEEP_SHM", 140);
  // 1000-byte messages in 256-byte first slots: the ring grows at once. Nobody listens yet.
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "bench", "--size", "1000", "--initial-slot", "256",
                      "--count", "10", "--rate", "0", "--history", "4", "--hold", "--id", "A"});
  REQUIRE(pub.expect("PUBLISHED 10"));
  for (int k = 0; k < 2; ++k) {  // the second one finds the ring as the first left it
    auto& sub = s.peer({"sub", "--channel", ch, "--type", "bench", "--publishers", "1", "--expect", "4"});
    INFO("subscriber " << k << ":\n" << sub.output());
    const auto st = of(sub.read_summaries(15000ms), ch);
    CHECK(st.num("received") == 4);
    CHECK(st.num("min") == 6);
    CHECK(st.num("last") == 9);
    CHECK(st.num("duplicates") == 0);
    CHECK(st.num("out_of_order") == 0);
    CHECK(st.num("drops") == 0);
    CHECK(st.num("bad_content") == 0);
    CHECK(st.str("paths") == "shm");
    CHECK(sub.wait() == 0);
  }
  pub.send("quit");
  CHECK(pub.wait() == 0);

  // While a stream runs: the kept ones, then every live one, nothing twice.
  const auto ch2 = unique_channel("KEEP_SHM_LIVE", 140);
  auto& stream = s.peer({"pub", "--channel", ch2, "--type", "pose", "--count", "0", "--rate", "500", "--history", "6",
                         "--id", "A"});
  REQUIRE(stream.expect("READY"));
  REQUIRE(wait_until([&] { return published(stream) >= 50; }, 10000ms, 20ms));
  auto& sub = s.peer({"sub", "--channel", ch2, "--type", "pose", "--publishers", "1", "--expect", "300"});
  INFO("stream subscriber:\n" << sub.output());
  const auto st = of(sub.read_summaries(15000ms), ch2);
  CHECK(st.num("duplicates") == 0);
  CHECK(st.num("out_of_order") == 0);
  CHECK(st.num("gaps") == 0);
  CHECK(st.num("drops") == 0);
  CHECK(st.num("received") >= 300);
  CHECK(st.num("first") == st.num("min"));
  CHECK(sub.wait() == 0);
  stream.send("quit");
  CHECK(stream.wait() == 0);
}
