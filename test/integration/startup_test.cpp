// The start-up race (issue 37): a program that publishes as soon as it starts, as LCM programs
// do, with a subscriber and `lcmx record` already running. Every message published after they
// subscribed reaches them, those published before discovery matched the pair included (the
// publisher's ring holds them: Reader::open's since). On a880031 the first messages were
// neither delivered nor counted.
#include <csignal>

#include "lcmx/log/eventlog.hpp"
#include "lcmx_examples/bench_t.hpp"
#include "support.hpp"

using namespace lcmx::it;

namespace {

// The bench_t messages of `channel` in the LCM log at `path` (seq order as logged).
std::vector<std::int64_t> startup_logged(const std::string& path, const std::string& channel) {
  std::vector<std::int64_t> out;
  try {
    auto r = lcmx::eventlog::Reader::open(path);
    lcmx::eventlog::Event e;
    while (r.next(e)) {
      if (e.channel != channel) continue;
      lcmx_examples::bench_t m;
      if (m.decode(e.data.data(), 0, static_cast<int>(e.data.size())) > 0) out.push_back(m.seq);
    }
  } catch (const lcmx::eventlog::Error&) {
  }
  return out;
}

}  // namespace

TEST_CASE("start-up race on one host: a publisher that publishes at once at start - a subscriber and lcmx record "
          "already running get 100 of 100 over shm, in order, once",
          "[integration][startup]") {
  Session s(148, 60000ms);
  TmpDir d;
  const std::string log = d.file("startup.lcmlog");
  const std::string ch = unique_channel("STARTUP", 148);
  auto& sub = s.peer({"sub", "--channel", ch, "--type", "bench", "--expect", "100", "--queue-depth", "256"});
  REQUIRE(sub.expect("READY"));
  auto& rec = s.spawn({LCMX_TOOL, "record", log, "-c", ch, "--json"}, {}, true);
  REQUIRE(rec.expect("lcmx record: recording to"));
  // --subscribers 0: it publishes as soon as it has advertised, before anyone matched it.
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "bench", "--size", "64", "--count", "100", "--rate", "200",
                      "--subscribers", "0", "--hold", "--id", "S"});
  REQUIRE(pub.expect("PUBLISHED", 20000ms));
  const auto st = of(sub.read_summaries(10000ms), ch);
  INFO(sub.output());
  CHECK(st.num("received") == 100);
  CHECK(st.num("first") == 0);
  CHECK(st.num("last") == 99);
  CHECK(st.num("duplicates") == 0);
  CHECK(st.num("out_of_order") == 0);
  CHECK(st.num("drops") == 0);
  CHECK(sub.wait() == 0);
  REQUIRE(wait_until([&] { return startup_logged(log, ch).size() >= 100; }, 10000ms, 20ms));
  rec.signal(SIGINT);
  REQUIRE(rec.wait(10000ms) == 0);
  INFO(rec.text());
  CHECK(json_num(json_line(rec.text()), "lost") == 0);
  const auto seqs = startup_logged(log, ch);
  REQUIRE(seqs.size() == 100);
  for (std::size_t i = 0; i < seqs.size(); ++i) CHECK(seqs[i] == static_cast<std::int64_t>(i));
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
