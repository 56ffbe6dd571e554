// The start-up race (issue 37): a program that publishes as soon as it starts, as LCM programs
// do, with a subscriber and `lcmx record` already running. Every message published after they
// subscribed reaches them, those published before discovery matched the pair included (the
// publisher's ring holds them: Reader::open's since). On a880031 the first messages were
// neither delivered nor counted.
#include <csignal>

#include "logged.hpp"
#include "support.hpp"

using namespace lcmx::it;

// What a program does at start (a configuration, then telemetry): 30 messages at 20 Hz. Its
// ring (the default 8 slots) holds 350 ms of them, far longer than discovery takes to match
// the pair on one host (a few ms; tens on a loaded machine): all 30 arrive.
TEST_CASE("start-up race on one host: a publisher that publishes at once at start - a subscriber and lcmx record "
          "already running get 30 of 30 over shm, in order, once",
          "[integration][startup]") {
  Session s(148, 60000ms);
  TmpDir d;
  const std::string log = d.file("startup.lcmlog");
  const std::string ch = unique_channel("STARTUP", 148);
  auto& sub = s.peer({"sub", "--channel", ch, "--type", "bench", "--expect", "30", "--queue-depth", "256"});
  REQUIRE(sub.expect("READY"));
  auto& rec = s.spawn({LCMX_TOOL, "record", log, "-c", ch, "--json"}, {}, true);
  REQUIRE(rec.expect("lcmx record: recording to"));
  // --subscribers 0: it publishes as soon as it has advertised, before anyone matched it.
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "bench", "--size", "64", "--count", "30", "--rate", "20",
                      "--subscribers", "0", "--hold", "--id", "S"});
  REQUIRE(pub.expect("PUBLISHED", 20000ms));
  const auto st = of(sub.read_summaries(10000ms), ch);
  INFO(sub.output());
  CHECK(st.num("received") == 30);
  CHECK(st.num("first") == 0);
  CHECK(st.num("last") == 29);
  CHECK(st.num("duplicates") == 0);
  CHECK(st.num("out_of_order") == 0);
  CHECK(st.num("drops") == 0);
  CHECK(sub.wait() == 0);
  REQUIRE(wait_until([&] { return logged_bench_seqs(log, ch).size() >= 30; }, 10000ms, 20ms));
  rec.signal(SIGINT);
  REQUIRE(rec.wait(10000ms) == 0);
  INFO(rec.text());
  CHECK(json_num(json_line(rec.text()), "lost") == 0);
  const auto seqs = logged_bench_seqs(log, ch);
  REQUIRE(seqs.size() == 30);
  for (std::size_t i = 0; i < seqs.size(); ++i) CHECK(seqs[i] == static_cast<std::int64_t>(i));
  pub.send("quit");
  CHECK(pub.wait() == 0);
}

// Faster than the ring can wait for discovery (200 Hz: the default ring holds 35 ms): what it
// no longer holds when the pair matches is counted in the subscriber's drops and record's
// lost, never silently missing; the rest arrives in order, once.
TEST_CASE("start-up race on one host at 200 Hz: what the ring no longer held when the pair matched is counted - "
          "received + drops = 100, in order, once",
          "[integration][startup]") {
  Session s(150, 60000ms);
  TmpDir d;
  const std::string log = d.file("startup_fast.lcmlog");
  const std::string ch = unique_channel("STARTUP_FAST", 150);
  auto& sub = s.peer({"sub", "--channel", ch, "--type", "bench", "--queue-depth", "256"});
  REQUIRE(sub.expect("READY"));
  auto& rec = s.spawn({LCMX_TOOL, "record", log, "-c", ch, "--json"}, {}, true);
  REQUIRE(rec.expect("lcmx record: recording to"));
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "bench", "--size", "64", "--count", "100", "--rate", "200",
                      "--subscribers", "0", "--hold", "--id", "F"});
  REQUIRE(pub.expect("PUBLISHED", 20000ms));
  poll_sub(sub, ch, [](const Summary& x) { return x.num("received") + x.num("drops") >= 100 && x.num("last") == 99; },
           10000ms);
  const auto st = of(sub.summaries("quit"), ch);
  INFO(sub.output());
  CHECK(st.num("received") + st.num("drops") == 100);
  CHECK(st.num("received") >= 1);
  CHECK(st.num("first") == st.num("drops"));  // only the first ones can have been lost
  CHECK(st.num("last") == 99);
  CHECK(st.num("duplicates") == 0);
  CHECK(st.num("out_of_order") == 0);
  CHECK(st.num("gaps") == 0);
  CHECK(sub.wait() == 0);
  REQUIRE(wait_until(
      [&] {
        const auto s = logged_bench_seqs(log, ch);  // the log read once per look
        return !s.empty() && s.back() == 99;
      },
      10000ms, 20ms));
  rec.signal(SIGINT);
  REQUIRE(rec.wait(10000ms) == 0);
  INFO(rec.text());
  const auto seqs = logged_bench_seqs(log, ch);
  CHECK(static_cast<std::int64_t>(seqs.size()) + json_num(json_line(rec.text()), "lost") == 100);
  for (std::size_t i = 1; i < seqs.size(); ++i) CHECK(seqs[i] == seqs[i - 1] + 1);
  pub.send("quit");
  CHECK(pub.wait() == 0);
}

TEST_CASE("start-up race in one process: a publisher made after the subscriber and publishing at once - 100 of 100 "
          "intra-process",
          "[integration][startup]") {
  Session s(149, 60000ms);
  const std::string ch = unique_channel("STARTUP_INTRA", 149);
  // --local-sub: a subscriber on another node of the publisher's own process, made first.
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "bench", "--size", "64", "--count", "100", "--rate", "200",
                      "--subscribers", "0", "--local-sub", "--queue-depth", "256", "--hold", "--id", "I"});
  REQUIRE(pub.expect("PUBLISHED", 20000ms));
  const auto st = of(pub.summaries("quit"), ch);
  INFO(pub.output());
  CHECK(st.num("received") == 100);
  CHECK(st.num("duplicates") == 0);
  CHECK(pub.wait() == 0);
}
