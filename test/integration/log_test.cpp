// `lcmx record`, `lcmx play`, `lcmx log info` with real processes: lcmx peers over shared
// memory, stock liblcm peers and Debian's lcm-logger / lcm-logplayer (inside network
// namespaces the tests create, on LCM's default URL).
#include <lcm/eventlog.h>
#include <sys/stat.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <iterator>

#include "lcmx/log/eventlog.hpp"
#include "lcmx_examples/bench_t.hpp"
#include "support.hpp"

using namespace lcmx::it;
namespace el = lcmx::eventlog;

namespace {

std::vector<el::Event> read_log(const std::string& path, el::Reader* keep = nullptr) {
  std::vector<el::Event> out;
  try {
    auto r = el::Reader::open(path);
    el::Event e;
    while (r.next(e)) out.push_back(e);
    if (keep) *keep = std::move(r);
  } catch (const el::Error&) {
  }
  return out;
}

std::size_t count_channel(const std::string& path, const std::string& channel) {
  std::size_t n = 0;
  for (const auto& e : read_log(path))
    if (e.channel == channel) ++n;
  return n;
}

std::uint64_t file_size(const std::string& p) {
  struct stat st{};
  return ::stat(p.c_str(), &st) == 0 ? static_cast<std::uint64_t>(st.st_size) : 0;
}

std::vector<std::byte> bench_bytes(std::int64_t seq, std::size_t size, const std::string& id) {
  lcmx_examples::bench_t m;
  m.seq = seq;
  m.send_ns = seq;
  m.size = static_cast<std::int32_t>(size);
  m.data.resize(size);
  for (std::size_t i = 0; i < size; ++i)
    m.data[i] = i < 8 ? (i < id.size() ? static_cast<std::uint8_t>(id[i]) : 0)
                      : static_cast<std::uint8_t>((i * 131u + static_cast<std::uint64_t>(seq) * 7u) & 0xffu);
  std::vector<std::byte> b(static_cast<std::size_t>(m.getEncodedSize()));
  m.encode(b.data(), 0, static_cast<int>(b.size()));
  return b;
}

}  // namespace

TEST_CASE("lcm-logger's log played by lcmx play reaches a typed lcmx subscriber over shm", "[integration][log]") {
  Session s(80, 60000ms);
  Netns ns;
  REQUIRE_NETNS_OR_SKIP(ns);
  TmpDir d;
  const std::string log = d.file("stock.lcmlog");
  const std::string ch = unique_channel("LOGGED", 80);
  const int n = 200;
  auto& logger = s.spawn({LCMX_IP, "netns", "exec", ns.name(), LCMX_LCM_LOGGER, "-q", "-f", "--flush-interval=10", log},
                         {"LCM_DEFAULT_URL"});
  // lcm-logger prints no ready line: a stock publisher sends until the log holds its messages.
  auto& warmup = s.spawn({LCMX_IP, "netns", "exec", ns.name(), LCMX_LCM_PEER, "pub", kLcmDefaultUrl,
                          ch + "_WARMUP", "400", "50", "16", "W"});
  REQUIRE(wait_until([&] { return count_channel(log, ch + "_WARMUP") > 0; }, 10000ms, 20ms));
  warmup.send("quit");
  auto& pub = s.spawn({LCMX_IP, "netns", "exec", ns.name(), LCMX_LCM_PEER, "pub", kLcmDefaultUrl, ch,
                       std::to_string(n), "200", "300", "S1"});
  REQUIRE(pub.expect("done", 20000ms) == "done " + std::to_string(n));
  // Stock LCM is lossy under load (lcm-logger loses a few datagrams on a busy 2-vCPU machine):
  // what matters here is that lcmx play delivers exactly what the log holds.
  if (!wait_until([&] { return count_channel(log, ch) == static_cast<std::size_t>(n); }, 5000ms, 20ms))
    WARN("lcm-logger logged only " << count_channel(log, ch) << " of " << n);
  logger.signal(SIGINT);
  CHECK(logger.wait(5000ms) == 0);
  const auto logged = static_cast<long long>(count_channel(log, ch));
  REQUIRE(logged >= n * 9 / 10);

  auto& sub = s.peer({"sub", "--channel", ch, "--type", "bench"});
  REQUIRE(sub.expect("READY"));
  const auto r = s.run({LCMX_TOOL, "play", log, "-c", ch, "--wait-subscribers", "1", "--delay", "0.1", "--speed",
                        "4", "--json"},
                       {}, 30000ms);
  INFO(r.out);
  CHECK(r.rc == 0);
  // The subscriber has the default 8 shm slots: on a loaded 2-vCPU CI machine it can be
  // descheduled for longer than 8 messages at 800 Hz take, and then counts drops. Every message
  // of the log must be accounted for: received, or counted as dropped; never lost uncounted.
  std::vector<Summary> sum;
  const bool accounted = wait_until(
      [&] {
        sum = sub.summaries("status");
        return sum.size() == 1 && sum[0].num("received") + sum[0].num("drops") >= logged;
      },
      20000ms, 50ms);
  INFO(sub.output());
  REQUIRE(accounted);
  if (sum[0].num("drops") > 0) WARN("the subscriber counted " << sum[0].num("drops") << " drops (slow under load)");
  CHECK(sum[0].num("received") + sum[0].num("drops") == logged);
  CHECK(sum[0].num("received") >= logged / 2);
  CHECK(sum[0].num("duplicates") == 0);
  CHECK(sum[0].num("out_of_order") == 0);
  CHECK(sum[0].num("bad_content") == 0);
  CHECK(sum[0].num("decode_errors") == 0);
  // play may have left already (then the summary lists no paths): its match event names the path.
  CHECK(sub.output().find("receives from process lcmx pid") != std::string::npos);
  CHECK(sub.output().find("node 'lcmx_play' (shm)") != std::string::npos);
  sub.send("quit");
  CHECK(sub.wait(5000ms) == 0);
  const auto j = json_line(r.out);
  CHECK(json_num(j, "published") == logged);
  // The fingerprint announced is bench_t's.
  char fp[20];
  std::snprintf(fp, sizeof fp, "%016llx", static_cast<unsigned long long>(lcmx_examples::bench_t::getHash()));
  CHECK(j.find(fp) != std::string::npos);
}

TEST_CASE("lcmx record of shm traffic is played by lcm-logplayer to a stock subscriber", "[integration][log]") {
  Session s(81, 60000ms);
  TmpDir d;
  const std::string log = d.file("rec.lcmlog");
  const std::string ch = unique_channel("REC", 81);
  const int n = 150;
  auto& rec = s.spawn({LCMX_TOOL, "record", log, "-c", ch, "--json"}, {}, true);
  REQUIRE(rec.expect("lcmx record: recording to"));
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "bench", "--size", "200", "--count", std::to_string(n),
                      "--rate", "300", "--subscribers", "1", "--id", "R1"});
  REQUIRE(pub.expect("PUBLISHED", 20000ms));
  REQUIRE(wait_until([&] { return count_channel(log, ch) == static_cast<std::size_t>(n); }, 10000ms, 20ms));
  rec.signal(SIGINT);
  REQUIRE(rec.wait(10000ms) == 0);
  const auto j = json_line(rec.text());
  INFO(rec.text());
  CHECK(json_num(j, "messages") == n);
  CHECK(json_num(j, "lost") == 0);

  Netns ns;
  REQUIRE_NETNS_OR_SKIP(ns);
  auto& sub = s.spawn({LCMX_IP, "netns", "exec", ns.name(), LCMX_LCM_PEER, "sub", kLcmDefaultUrl, ch,
                       std::to_string(n), "30000"});
  REQUIRE(sub.expect("ready"));
  const auto r = s.run({LCMX_IP, "netns", "exec", ns.name(), LCMX_LCM_LOGPLAYER, "-s", "4", log},
                       {"LCM_DEFAULT_URL"}, 30000ms);
  INFO(r.out);
  CHECK(r.rc == 0);
  const auto sum = sub.read_summaries(20000ms);
  REQUIRE(sum.size() == 1);
  CHECK(sum[0].num("received") == n);
  CHECK(sum[0].num("bad_content") == 0);
  CHECK(sum[0].num("duplicates") == 0);
  CHECK(sum[0].num("out_of_order") == 0);
}

TEST_CASE("2.5 MB messages recorded from shared memory play back intact", "[integration][log]") {
  Session s(82, 60000ms);
  TmpDir d;
  const std::string log = d.file("big.lcmlog");
  const std::string ch = unique_channel("BIG", 82);
  const int n = 12;
  auto& rec = s.spawn({LCMX_TOOL, "record", log, "-c", ch, "--json"}, {}, true);
  REQUIRE(rec.expect("lcmx record: recording to"));
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "bench", "--size", "2500000", "--count", std::to_string(n),
                      "--rate", "20", "--subscribers", "1", "--id", "BIG"});
  REQUIRE(pub.expect("PUBLISHED", 30000ms));
  REQUIRE(wait_until([&] { return count_channel(log, ch) == static_cast<std::size_t>(n); }, 15000ms, 50ms));
  rec.signal(SIGINT);
  REQUIRE(rec.wait(10000ms) == 0);
  CHECK(json_num(json_line(rec.text()), "lost") == 0);
  for (const auto& e : read_log(log)) CHECK(e.data.size() > 2'500'000u);

  auto& sub = s.peer({"sub", "--channel", ch, "--type", "bench", "--expect", std::to_string(n)});
  REQUIRE(sub.expect("READY"));
  const auto r = s.run({LCMX_TOOL, "play", log, "--wait-subscribers", "1", "--delay", "0.1", "--json"}, {}, 30000ms);
  INFO(r.out);
  CHECK(r.rc == 0);
  const auto sum = sub.read_summaries(20000ms);
  REQUIRE(sum.size() == 1);
  CHECK(sum[0].num("received") == n);
  CHECK(sum[0].num("bad_content") == 0);
  CHECK(sum[0].num("decode_errors") == 0);
}

TEST_CASE("record/play round trip: channel, data and order identical, timestamps within 1 ms at speed 1",
          "[integration][log]") {
  Session s(83, 60000ms);
  TmpDir d;
  const std::string src = d.file("src.lcmlog"), out = d.file("out.lcmlog");
  const std::string a = unique_channel("RT_A", 83), b = unique_channel("RT_B", 83), c = unique_channel("RT_C", 83);
  // 150 events over ~1.2 s on three channels, 3..13 ms apart, sizes 16 B .. 300 KB.
  {
    auto w = el::Writer::open(src, el::OpenMode::create);
    std::int64_t ts = 1'700'000'000'000'000;
    for (int i = 0; i < 150; ++i) {
      const std::string& ch = i % 3 == 0 ? a : (i % 3 == 1 ? b : c);
      const std::size_t size = i % 25 == 24 ? 300'000 : 16 + static_cast<std::size_t>(i) * 11;
      w.write(ts, ch, bench_bytes(i, size, "RT"));
      ts += 3000 + (i * 7919) % 10000;
    }
    w.close();
  }
  auto& rec = s.spawn({LCMX_TOOL, "record", out, "-c", unique_channel("RT_.", 83), "--rt-priority", "5", "--json"},
                      {}, true);
  REQUIRE(rec.expect("lcmx record: recording to"));
  const auto r = s.run({LCMX_TOOL, "play", src, "--wait-subscribers", "3", "--delay", "0.2", "--rt-priority", "5",
                        "--json"},
                       {}, 30000ms);
  INFO(r.out);
  REQUIRE(r.rc == 0);
  const auto want = read_log(src);
  REQUIRE(wait_until([&] { return read_log(out).size() >= want.size(); }, 10000ms, 20ms));
  rec.signal(SIGINT);
  REQUIRE(rec.wait(10000ms) == 0);
  const auto got = read_log(out);
  REQUIRE(got.size() == want.size());
  // Timestamps: the recording's are the original ones shifted by when playing started; the
  // shift is taken as the median difference (not event 0's alone, whose own delivery delay
  // would count against every other event).
  std::vector<std::int64_t> shift;
  for (std::size_t i = 0; i < want.size(); ++i) {
    INFO("event " << i);
    CHECK(got[i].channel == want[i].channel);
    CHECK(got[i].data == want[i].data);
    CHECK(got[i].number == static_cast<std::int64_t>(i));
    shift.push_back(got[i].timestamp_us - want[i].timestamp_us);
  }
  auto sorted = shift;
  std::sort(sorted.begin(), sorted.end());
  const std::int64_t median = sorted[sorted.size() / 2];
  std::vector<double> dev_ms;
  for (const auto v : shift) dev_ms.push_back(std::abs(static_cast<double>(v - median)) / 1000.0);
  std::sort(dev_ms.begin(), dev_ms.end());
  INFO("|recorded - original| after the shift: p50 " << dev_ms[dev_ms.size() / 2] << " ms, p99 "
       << dev_ms[dev_ms.size() * 99 / 100] << " ms, max " << dev_ms.back() << " ms");
  // Within 1 ms. The suite runs on 2 shared vCPUs, often with a load of 5-9: a preempted
  // player or recorder process (both sleep between messages) exceeds it for some events, so
  // player and recorder run SCHED_FIFO (--rt-priority) and the check is: the median within 0.5 ms,
  // 90 % within 1 ms, none beyond 20 ms (a broken schedule — drift, wrong speed, lagging —
  // fails all three).
  CHECK(dev_ms[dev_ms.size() / 2] <= 0.5);
  CHECK(dev_ms[dev_ms.size() * 90 / 100] <= 1.0);
  CHECK(dev_ms.back() <= 20.0);
}

TEST_CASE("truncated, corrupt and garbage logs: log info finds the damage, play stops or resumes and says where",
          "[integration][log]") {
  Session s(84, 60000ms);
  TmpDir d;
  const std::string ch = unique_channel("DMG", 84);
  const std::string good = d.file("good.lcmlog");
  {
    auto w = el::Writer::open(good, el::OpenMode::create);
    for (int i = 0; i < 20; ++i) w.write(1'700'000'000'000'000 + i * 1000, ch, bench_bytes(i, 500, "D"));
    w.close();
  }
  const auto events = read_log(good);
  REQUIRE(events.size() == 20);
  std::ifstream in(good, std::ios::binary);
  const std::vector<char> bytes{std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
  auto spit = [&](const std::string& name, const std::vector<char>& b) {
    std::ofstream f(d.file(name), std::ios::binary);
    f.write(b.data(), static_cast<std::streamsize>(b.size()));
    return d.file(name);
  };

  SECTION("truncated inside event 15") {
    const auto off = events[15].offset;
    const auto log = spit("cut.lcmlog", {bytes.begin(), bytes.begin() + static_cast<long>(off + 100)});
    const auto info = s.run({LCMX_TOOL, "log", "info", log, "--json"});
    INFO(info.out);
    CHECK(info.rc == 0);
    CHECK(json_num(info.out, "events") == 15);
    CHECK(info.out.find("\"kind\":\"truncated\",\"offset\":" + std::to_string(off) + ",\"length\":100") !=
          std::string::npos);
    const auto text = s.run({LCMX_TOOL, "log", "info", log});
    CHECK(text.out.find("truncated at offset " + std::to_string(off)) != std::string::npos);
    const auto play = s.run({LCMX_TOOL, "play", log, "--fast", "--delay", "0", "--json"});
    INFO(play.out);
    CHECK(play.rc == 0);
    CHECK(json_num(json_line(play.out), "published") == 15);
    CHECK(play.out.find("stopped: the log ends with truncated bytes at offset " + std::to_string(off)) !=
          std::string::npos);
  }
  SECTION("event 5's length field corrupted: skipped, reported, the rest plays") {
    auto b = bytes;
    b[events[5].offset + 25] = '\x55';
    const auto log = spit("corrupt.lcmlog", b);
    const auto play = s.run({LCMX_TOOL, "play", log, "--fast", "--delay", "0", "--json"});
    INFO(play.out);
    CHECK(play.rc == 0);
    CHECK(json_num(json_line(play.out), "published") == 19);
    CHECK(play.out.find("damaged log: " + std::to_string(events[6].offset - events[5].offset) +
                        " bytes skipped at offset " + std::to_string(events[5].offset)) != std::string::npos);
    const auto stop = s.run({LCMX_TOOL, "play", log, "--fast", "--delay", "0", "--stop-on-damage", "--json"});
    CHECK(json_num(json_line(stop.out), "published") == 5);
  }
  SECTION("garbage only") {
    std::vector<char> junk(50'000);
    for (std::size_t i = 0; i < junk.size(); ++i) junk[i] = static_cast<char>((i * 2654435761u) >> 13);
    const auto log = spit("junk.lcmlog", junk);
    const auto play = s.run({LCMX_TOOL, "play", log});
    CHECK(play.rc == 1);
    CHECK(play.out.find("holds no readable event") != std::string::npos);
    const auto info = s.run({LCMX_TOOL, "log", "info", log, "--json"});
    CHECK(info.rc == 0);
    CHECK(json_num(info.out, "events") == 0);
    CHECK(json_num(info.out, "damaged_bytes") == 50'000);
    const auto text = s.run({LCMX_TOOL, "log", "info", log});
    CHECK(text.out.find("not an LCM log") != std::string::npos);
  }
  SECTION("recorded discovery beacons are not played (they would announce dead processes)") {
    const auto log = d.file("beacons.lcmlog");
    {
      auto w = el::Writer::open(log, el::OpenMode::create);
      for (int i = 0; i < 6; ++i) {
        w.write(1'700'000'000'000'000 + i * 1000, "LCMX_BEACON", bench_bytes(i, 100, "B"));
        w.write(1'700'000'000'000'500 + i * 1000, ch, bench_bytes(i, 100, "D"));
      }
      w.close();
    }
    const auto play = s.run({LCMX_TOOL, "play", log, "--fast", "--delay", "0", "--json"});
    INFO(play.out);
    CHECK(play.rc == 0);
    CHECK(json_num(json_line(play.out), "published") == 6);
    CHECK(play.out.find("6 events of LCMX_BEACON (lcmx's discovery beacons) not played") != std::string::npos);
  }
  SECTION("not a log file at all") {
    const auto play = s.run({LCMX_TOOL, "play", d.file("missing.lcmlog")});
    CHECK(play.rc == 1);
    CHECK(play.out.find("cannot open") != std::string::npos);
  }
}

TEST_CASE("SIGKILL of the recorder mid-write leaves a log readable up to its last complete event",
          "[integration][log]") {
  Session s(85, 60000ms);
  TmpDir d;
  const std::string log = d.file("killed.lcmlog");
  const std::string ch = unique_channel("KILL", 85);
  auto& rec = s.spawn({LCMX_TOOL, "record", log, "-c", ch, "--flush-interval", "5"}, {}, true);
  REQUIRE(rec.expect("lcmx record: recording to"));
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "bench", "--size", "300000", "--count", "0", "--rate", "200",
                      "--subscribers", "1", "--id", "K"});
  REQUIRE(pub.expect("MATCHED", 20000ms));
  REQUIRE(wait_until([&] { return file_size(log) > 8'000'000; }, 20000ms, 5ms));
  rec.kill9();
  pub.send("quit");
  el::Reader r = el::Reader::open(log);
  const auto got = read_log(log, &r);
  INFO("events " << got.size() << ", damage " << r.damage_count());
  REQUIRE(got.size() > 20);
  CHECK(r.damage_count() <= 1);
  if (r.damage_count() == 1) {
    CHECK(r.damage()[0].kind == el::Damage::Kind::truncated);
    CHECK(r.damage()[0].offset + r.damage()[0].length == file_size(log));
  }
  for (std::size_t i = 0; i < got.size(); ++i) {
    CHECK(got[i].number == static_cast<std::int64_t>(i));
    lcmx_examples::bench_t m;
    REQUIRE(m.decode(got[i].data.data(), 0, static_cast<int>(got[i].data.size())) > 0);
  }
  // liblcm's reader (lcm-logplayer's) reads the same events.
  lcm_eventlog_t* l = lcm_eventlog_create(log.c_str(), "r");
  REQUIRE(l != nullptr);
  std::size_t n = 0;
  while (lcm_eventlog_event_t* e = lcm_eventlog_read_next_event(l)) {
    ++n;
    lcm_eventlog_free_event(e);
  }
  lcm_eventlog_destroy(l);
  CHECK(n == got.size());
}

TEST_CASE("lcmx record hears stock LCM programs on the host-local group, lcmx play --udp reaches them",
          "[integration][log][interop]") {
  Session s(86, 60000ms);
  Netns ns;
  REQUIRE_NETNS_OR_SKIP(ns);
  TmpDir d;
  const std::string log = d.file("stock.lcmlog");
  const std::string ch = unique_channel("STOCK", 86);
  const int n = 100;
  // Both on LCM's defaults (no LCM_DEFAULT_URL, no LCMX_DISCOVERY_URL).
  auto& rec = s.spawn({LCMX_IP, "netns", "exec", ns.name(), LCMX_TOOL, "record", log, "-c", ch + ".*", "--json"},
                      {"LCMX_DISCOVERY_URL"}, true);
  REQUIRE(rec.expect("lcmx record: recording to"));
  auto& pub = s.spawn({LCMX_IP, "netns", "exec", ns.name(), LCMX_LCM_PEER, "pub", kLcmDefaultUrl, ch,
                       std::to_string(n), "200", "100", "ST"});
  REQUIRE(pub.expect("done", 20000ms));
  REQUIRE(wait_until([&] { return count_channel(log, ch) == static_cast<std::size_t>(n); }, 10000ms, 20ms));
  rec.signal(SIGINT);
  REQUIRE(rec.wait(10000ms) == 0);
  CHECK(json_num(json_line(rec.text()), "lost") == 0);
  const auto got = read_log(log);
  REQUIRE(got.size() == static_cast<std::size_t>(n));
  for (std::size_t i = 0; i < got.size(); ++i) {
    lcmx_examples::bench_t m;
    REQUIRE(m.decode(got[i].data.data(), 0, static_cast<int>(got[i].data.size())) > 0);
    CHECK(m.seq == static_cast<std::int64_t>(i));
    CHECK(m.size == 100);
  }

  auto& sub = s.spawn({LCMX_IP, "netns", "exec", ns.name(), LCMX_LCM_PEER, "sub", kLcmDefaultUrl, ch + "_OUT",
                       std::to_string(n), "30000"});
  REQUIRE(sub.expect("ready"));
  const auto r = s.run({LCMX_IP, "netns", "exec", ns.name(), LCMX_TOOL, "play", log, "--udp", "--remap",
                        ch + "=" + ch + "_OUT", "--speed", "4", "--delay", "0.1"},
                       {"LCMX_DISCOVERY_URL"}, 30000ms);
  INFO(r.out);
  CHECK(r.rc == 0);
  const auto sum = sub.read_summaries(20000ms);
  REQUIRE(sum.size() == 1);
  CHECK(sum[0].num("received") == n);
  CHECK(sum[0].num("bad_content") == 0);
  CHECK(sum[0].num("out_of_order") == 0);
}

TEST_CASE("record/play/log: --help for each verb, clear errors for bad options", "[integration][log][cli]") {
  Session s(87, 30000ms);
  for (const auto& verb : std::vector<std::vector<std::string>>{{"record"}, {"play"}, {"log", "info"}}) {
    auto argv = std::vector<std::string>{LCMX_TOOL};
    argv.insert(argv.end(), verb.begin(), verb.end());
    argv.push_back("--help");
    const auto r = s.run(argv);
    INFO(r.out);
    CHECK(r.rc == 0);
    CHECK(r.out.find(verb.back() + " [OPTIONS]") != std::string::npos);
    CHECK(r.out.find("--json") != std::string::npos);
  }
  const auto bad = s.run({LCMX_TOOL, "record", "-c", "(unclosed", "/tmp/never.lcmlog"});
  CHECK(bad.rc == 2);
  CHECK(bad.out.find("bad channel expression") != std::string::npos);
  TmpDir d;
  { std::ofstream(d.file("exists.lcmlog")) << "x"; }
  const auto exists = s.run({LCMX_TOOL, "record", d.file("exists.lcmlog")});
  CHECK(exists.rc == 1);
  CHECK(exists.out.find("exists: give --force") != std::string::npos);
  const auto remap = s.run({LCMX_TOOL, "play", d.file("exists.lcmlog"), "--remap", "NOEQUALS"});
  CHECK(remap.rc == 2);
  CHECK(remap.out.find("expected FROM=TO") != std::string::npos);
  // A bad number is named plainly (not "not in range 0 to 1797693134862315708...").
  const auto speed = s.run({LCMX_TOOL, "play", d.file("exists.lcmlog"), "--speed", "0"});
  CHECK(speed.rc == 2);
  CHECK(speed.out.find("--speed: must be greater than 0 (got 0)") != std::string::npos);
  // A missing or unknown argument exits 2, as --help says (not CLI11's own 105-109).
  CHECK(s.run({LCMX_TOOL, "play"}).rc == 2);
  CHECK(s.run({LCMX_TOOL, "record", "--no-such-option"}).rc == 2);
  // A repeatable option takes one value: FILE after it is still FILE, not a second value.
  const auto remap_first = s.run({LCMX_TOOL, "play", "--remap", "A=B", d.file("exists.lcmlog")});
  INFO(remap_first.out);
  CHECK(remap_first.rc == 1);
  CHECK(remap_first.out.find("no readable event") != std::string::npos);
  const auto exclude_first =
      s.run({LCMX_TOOL, "record", "-x", "POSE", d.file("exists.lcmlog"), "--max-duration", "1"});
  INFO(exclude_first.out);
  CHECK(exclude_first.rc == 1);
  CHECK(exclude_first.out.find("exists: give --force") != std::string::npos);
  // A recording that cannot start (here its group names an interface this host lacks) creates
  // no file, so the same command, run again, fails for the same reason, not because the file
  // exists.
  for (int attempt = 0; attempt < 2; ++attempt) {
    const auto failed = s.run({LCMX_TOOL, "record", d.file("never.lcmlog"), "--max-duration", "1"},
                              {"LCMX_DISCOVERY_URL=" + unique_url(87) + "&iface=lcmxnoif0"});
    INFO(failed.out);
    CHECK(failed.rc == 1);
    CHECK(failed.out.find("no interface named 'lcmxnoif0'") != std::string::npos);
    CHECK_FALSE(std::filesystem::exists(d.file("never.lcmlog")));
  }
}

TEST_CASE("on a terminal (tmux): play shows a progress bar, starts paused, space resumes, record shows a status line",
          "[integration][log][tty]") {
  Session s(88, 60000ms);
  TmpDir d;
  const std::string ch = unique_channel("TTY", 88);
  const std::string log = d.file("tty.lcmlog");
  {
    auto w = el::Writer::open(log, el::OpenMode::create);
    for (int i = 0; i < 40; ++i) w.write(1'700'000'000'000'000 + i * 50'000, ch, bench_bytes(i, 100, "T"));
    w.close();
  }
  const Tmux tmux("lcmxit_" + std::to_string(::getpid()));
  auto pane = [&](const std::string& session) { return tmux.pane(session); };
  // The session's shell gets this test's environment (discovery group) through tmux's.
  const std::string env = "LCMX_DISCOVERY_URL='" + s.url + "' LCMX_BEACON_PERIOD_MS=100 LCMX_LEASE_MS=600 ";
  REQUIRE(tmux.run({"new-session", "-d", "-s", "play", "-x", "160", "-y", "20",
                env + LCMX_TOOL + " play " + log + " --paused --delay 0; echo PLAY-EXIT=$?; sleep 30"})
              .rc == 0);
  REQUIRE(wait_until([&] { return pane("play").find("PAUSED") != std::string::npos; }, 10000ms, 20ms));
  CHECK(pane("play").find("[") != std::string::npos);
  CHECK(pane("play").find("PLAY-EXIT") == std::string::npos);  // paused: it waits
  REQUIRE(tmux.run({"send-keys", "-t", "play", " "}).rc == 0);
  INFO(pane("play"));
  REQUIRE(wait_until([&] { return pane("play").find("PLAY-EXIT=0") != std::string::npos; }, 15000ms, 20ms));
  CHECK(pane("play").find("published 40 of 40 events") != std::string::npos);

  const std::string rec_log = d.file("tty-rec.lcmlog");
  REQUIRE(tmux.run({"new-session", "-d", "-s", "rec", "-x", "200", "-y", "20",
                env + LCMX_TOOL + " record " + rec_log + " -c '" + ch + "'; echo REC-EXIT=$?; sleep 30"})
              .rc == 0);
  REQUIRE(wait_until([&] { return pane("rec").find("msgs") != std::string::npos; }, 10000ms, 20ms));
  // Not --fast: 40 messages at once would overrun the publisher's 8-slot shm ring.
  const auto r = s.run({LCMX_TOOL, "play", log, "--speed", "10", "--wait-subscribers", "1", "--delay", "0.1"}, {},
                       20000ms);
  CHECK(r.rc == 0);
  const bool all = wait_until([&] { return pane("rec").find("40 msgs") != std::string::npos; }, 10000ms, 20ms);
  INFO(pane("rec"));
  REQUIRE(all);
  REQUIRE(tmux.run({"send-keys", "-t", "rec", "C-c"}).rc == 0);
  REQUIRE(wait_until([&] { return pane("rec").find("REC-EXIT=0") != std::string::npos; }, 10000ms, 20ms));
  INFO(pane("rec"));
  CHECK(pane("rec").find("40 messages") != std::string::npos);
  CHECK(read_log(rec_log).size() == 40);
}

TEST_CASE("record --increment --split-mb starts FILE.NN+1 files, SIGHUP starts the next one, nothing is lost",
          "[integration][log]") {
  Session s(89, 60000ms);
  TmpDir d;
  const std::string base = d.file("split.lcmlog");
  const std::string ch = unique_channel("SPLIT", 89);
  const int n = 200;
  auto& rec = s.spawn({LCMX_TOOL, "record", base, "-c", ch, "-i", "--split-mb", "0.05", "--flush-interval", "10",
                       "--json"},
                      {}, true);
  REQUIRE(rec.expect("lcmx record: recording to " + base + ".00"));
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "bench", "--size", "1000", "--count", std::to_string(n),
                      "--rate", "400", "--subscribers", "1", "--id", "SP", "--hold"});
  REQUIRE(pub.expect("PUBLISHED", 20000ms));
  auto total = [&] {
    std::size_t t = 0;
    for (int i = 0; i < 100; ++i) {
      char suffix[16];
      std::snprintf(suffix, sizeof suffix, ".%02d", i);
      if (file_size(base + suffix) == 0 && i > 0) break;
      t += count_channel(base + suffix, ch);
    }
    return t;
  };
  REQUIRE(wait_until([&] { return total() == static_cast<std::size_t>(n); }, 10000ms, 20ms));
  const auto files_before = [&] {
    int k = 0;
    while (file_size(base + (k < 10 ? ".0" : ".") + std::to_string(k)) > 0) ++k;
    return k;
  }();
  CHECK(files_before >= 3);  // 200 x ~1 KB in 50 KB files
  rec.signal(SIGHUP);
  char next[16];
  std::snprintf(next, sizeof next, ".%02d", files_before);
  // The next file exists (empty until something comes) once the writer has seen the SIGHUP.
  CHECK(wait_until([&] { return ::access((base + next).c_str(), F_OK) == 0; }, 5000ms, 10ms));
  pub.send("quit");
  rec.signal(SIGINT);
  REQUIRE(rec.wait(10000ms) == 0);
  INFO(rec.text());
  CHECK(json_num(json_line(rec.text()), "messages") == n);
  CHECK(json_num(json_line(rec.text()), "lost") == 0);
  // Each file numbers its events from 0, and holds whole events only.
  for (int i = 0; i < files_before; ++i) {
    char suffix[16];
    std::snprintf(suffix, sizeof suffix, ".%02d", i);
    el::Reader r = el::Reader::open(base + suffix);
    const auto evs = read_log(base + suffix, &r);
    CHECK(r.damage_count() == 0);
    if (!evs.empty()) CHECK(evs.front().number == 0);
  }
}
