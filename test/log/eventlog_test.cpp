// lcmx::eventlog against liblcm's lcm_eventlog (the reference: what lcm-logger writes and
// lcm-logplayer reads), and the reader on damaged files.
#include <catch2/catch.hpp>
#include <lcm/eventlog.h>
#include <unistd.h>

#include <cstdio>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include "lcmx/log/eventlog.hpp"
#include "lcmx/test/tmp_dir.hpp"

namespace el = lcmx::eventlog;

namespace {

struct TmpDir : lcmx::test::TmpDir {
  TmpDir() : lcmx::test::TmpDir("lcmx_eventlog") {}
};

std::vector<char> slurp(const std::string& p) {
  std::ifstream f(p, std::ios::binary);
  return {std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>()};
}
void spit(const std::string& p, const std::vector<char>& b) {
  std::ofstream f(p, std::ios::binary | std::ios::trunc);
  f.write(b.data(), static_cast<std::streamsize>(b.size()));
}

struct Ev {
  std::int64_t ts;
  std::string channel;
  std::vector<std::byte> data;
};

std::vector<Ev> sample_events() {
  std::vector<Ev> v;
  for (int i = 0; i < 50; ++i) {
    Ev e{1'700'000'000'000'000 + i * 1234, "CH_" + std::to_string(i % 5), {}};
    // sizes 0, small, and some above the writer's direct-write threshold (64 KiB)
    const std::size_t n = i % 10 == 9 ? 100'000 + static_cast<std::size_t>(i) : static_cast<std::size_t>(i * 37);
    for (std::size_t k = 0; k < n; ++k) e.data.push_back(static_cast<std::byte>((k * 31 + static_cast<std::size_t>(i)) & 0xff));
    v.push_back(std::move(e));
  }
  return v;
}

void write_lcmx(const std::string& path, const std::vector<Ev>& evs) {
  auto w = el::Writer::open(path, el::OpenMode::create);
  for (const auto& e : evs) w.write(e.ts, e.channel, e.data);
  w.close();
}

void write_liblcm(const std::string& path, const std::vector<Ev>& evs) {
  lcm_eventlog_t* log = lcm_eventlog_create(path.c_str(), "w");
  REQUIRE(log != nullptr);
  for (const auto& e : evs) {
    lcm_eventlog_event_t le{};
    le.timestamp = e.ts;
    le.channellen = static_cast<std::int32_t>(e.channel.size());
    le.datalen = static_cast<std::int32_t>(e.data.size());
    le.channel = const_cast<char*>(e.channel.c_str());
    le.data = const_cast<std::byte*>(e.data.data());
    REQUIRE(lcm_eventlog_write_event(log, &le) == 0);
  }
  lcm_eventlog_destroy(log);
}

std::vector<el::Event> read_all(const std::string& path, el::Reader* keep = nullptr) {
  auto r = el::Reader::open(path);
  std::vector<el::Event> out;
  el::Event e;
  while (r.next(e)) out.push_back(e);
  if (keep) *keep = std::move(r);
  return out;
}

}  // namespace

TEST_CASE("Writer output is byte-identical to liblcm's lcm_eventlog_write_event") {
  TmpDir d;
  const auto evs = sample_events();
  write_lcmx(d.file("lcmx.log"), evs);
  write_liblcm(d.file("liblcm.log"), evs);
  const auto a = slurp(d.file("lcmx.log")), b = slurp(d.file("liblcm.log"));
  REQUIRE(a.size() == b.size());
  CHECK(a == b);
}

TEST_CASE("Reader reads liblcm's log, and liblcm reads the Writer's") {
  TmpDir d;
  const auto evs = sample_events();
  write_liblcm(d.file("liblcm.log"), evs);
  const auto got = read_all(d.file("liblcm.log"));
  REQUIRE(got.size() == evs.size());
  for (std::size_t i = 0; i < evs.size(); ++i) {
    CHECK(got[i].number == static_cast<std::int64_t>(i));
    CHECK(got[i].timestamp_us == evs[i].ts);
    CHECK(got[i].channel == evs[i].channel);
    CHECK(got[i].data == evs[i].data);
    CHECK(got[i].size == evs[i].data.size());
  }
  write_lcmx(d.file("lcmx.log"), evs);
  lcm_eventlog_t* log = lcm_eventlog_create(d.file("lcmx.log").c_str(), "r");
  REQUIRE(log != nullptr);
  std::size_t n = 0;
  while (lcm_eventlog_event_t* e = lcm_eventlog_read_next_event(log)) {
    REQUIRE(n < evs.size());
    CHECK(std::string(e->channel, static_cast<std::size_t>(e->channellen)) == evs[n].channel);
    CHECK(static_cast<std::size_t>(e->datalen) == evs[n].data.size());
    ++n;
    lcm_eventlog_free_event(e);
  }
  lcm_eventlog_destroy(log);
  CHECK(n == evs.size());
}

TEST_CASE("Reader: a truncated last event is reported as truncated at its offset, at every cut") {
  TmpDir d;
  const auto evs = sample_events();
  write_lcmx(d.file("full.log"), evs);
  const auto full = slurp(d.file("full.log"));
  el::Reader keep = el::Reader::open(d.file("full.log"));
  const auto all = read_all(d.file("full.log"), &keep);
  REQUIRE(all.size() == evs.size());
  CHECK(keep.damage_count() == 0);
  const std::uint64_t last = all.back().offset;
  // Cut inside the last event (which is 100 KB: also inside its data), byte by byte near the
  // header and in steps through the data.
  for (std::uint64_t cut = last + 1; cut < full.size(); cut += (cut < last + 64 ? 1 : 997)) {
    spit(d.file("cut.log"), {full.begin(), full.begin() + static_cast<long>(cut)});
    el::Reader r = el::Reader::open(d.file("cut.log"));
    const auto got = read_all(d.file("cut.log"), &r);
    INFO("cut at " << cut);
    REQUIRE(got.size() == evs.size() - 1);
    REQUIRE(r.damage().size() == 1);
    CHECK(r.damage()[0].kind == el::Damage::Kind::truncated);
    CHECK(r.damage()[0].offset == last);
    CHECK(r.damage()[0].length == cut - last);
  }
}

TEST_CASE("Reader: garbage in the middle is skipped, reported, and reading resumes at the next event") {
  TmpDir d;
  const auto evs = sample_events();
  write_lcmx(d.file("full.log"), evs);
  auto bytes = slurp(d.file("full.log"));
  const auto all = read_all(d.file("full.log"));
  SECTION("bytes overwritten inside event 10 (its length field)") {
    const auto off = all[10].offset;
    bytes[off + 24] = '\x7f';  // data length becomes ~2 GB: a hostile length
    spit(d.file("bad.log"), bytes);
    el::Reader r = el::Reader::open(d.file("bad.log"));
    const auto got = read_all(d.file("bad.log"), &r);
    CHECK(got.size() == evs.size() - 1);
    REQUIRE(r.damage().size() == 1);
    CHECK(r.damage()[0].kind == el::Damage::Kind::corrupt);
    CHECK(r.damage()[0].offset == off);
    CHECK(r.damage()[0].length == all[11].offset - off);
    CHECK(got[10].channel == evs[11].channel);
    CHECK(got[10].data == evs[11].data);
  }
  SECTION("garbage inserted between events 20 and 21, including a false sync word") {
    const auto off = all[21].offset;
    std::vector<char> junk = {'x', '\xED', '\xA1', '\xDA', '\x01', 'y', 'z'};
    bytes.insert(bytes.begin() + static_cast<long>(off), junk.begin(), junk.end());
    spit(d.file("bad.log"), bytes);
    el::Reader r = el::Reader::open(d.file("bad.log"));
    const auto got = read_all(d.file("bad.log"), &r);
    // Event 20 is not followed by a sync word any more: it is taken as damaged too (its
    // length cannot be trusted), the rest is read.
    CHECK(got.size() >= evs.size() - 1);
    REQUIRE(r.damage_count() == 1);
    CHECK(r.damage()[0].offset == all[20].offset);
    CHECK(got.back().data == evs.back().data);
  }
  SECTION("a file of garbage only") {
    std::vector<char> junk(100'000);
    for (std::size_t i = 0; i < junk.size(); ++i) junk[i] = static_cast<char>((i * 7919) >> 3);
    spit(d.file("junk.log"), junk);
    el::Reader r = el::Reader::open(d.file("junk.log"));
    CHECK(read_all(d.file("junk.log"), &r).empty());
    REQUIRE(r.damage_count() == 1);
    CHECK(r.damaged_bytes() == junk.size());
  }
  SECTION("an empty file") {
    spit(d.file("empty.log"), {});
    el::Reader r = el::Reader::open(d.file("empty.log"));
    CHECK(read_all(d.file("empty.log"), &r).empty());
    CHECK(r.damage_count() == 0);
  }
}

TEST_CASE("Writer: append continues the numbering and cuts a torn last event") {
  TmpDir d;
  const auto evs = sample_events();
  write_lcmx(d.file("a.log"), {evs.begin(), evs.begin() + 10});
  auto bytes = slurp(d.file("a.log"));
  bytes.resize(bytes.size() - 5);  // event 9 torn (a recorder killed mid-write)
  spit(d.file("a.log"), bytes);
  {
    auto w = el::Writer::open(d.file("a.log"), el::OpenMode::append);
    for (int i = 10; i < 20; ++i) w.write(evs[static_cast<std::size_t>(i)].ts, evs[static_cast<std::size_t>(i)].channel, evs[static_cast<std::size_t>(i)].data);
    w.close();
  }
  el::Reader r = el::Reader::open(d.file("a.log"));
  const auto got = read_all(d.file("a.log"), &r);
  CHECK(r.damage_count() == 0);
  REQUIRE(got.size() == 19);
  CHECK(got[8].number == 8);
  CHECK(got[9].number == 9);
  CHECK(got[9].data == evs[10].data);
  CHECK_THROWS_AS(el::Writer::open(d.file("a.log"), el::OpenMode::create), el::Error);
}

TEST_CASE("Reader: data_prefix reads headers and a prefix only, errors are typed") {
  TmpDir d;
  const auto evs = sample_events();
  write_lcmx(d.file("a.log"), evs);
  el::ReaderOptions o;
  o.data_prefix = 8;
  auto r = el::Reader::open(d.file("a.log"), o);
  el::Event e;
  std::size_t n = 0;
  while (r.next(e)) {
    CHECK(e.size == evs[n].data.size());
    CHECK(e.data.size() == std::min<std::size_t>(8, evs[n].data.size()));
    ++n;
  }
  CHECK(n == evs.size());
  CHECK_THROWS_AS(el::Reader::open(d.file("missing.log")), el::Error);
  CHECK_THROWS_AS(el::Reader::open(d.path), el::Error);  // a directory
}

TEST_CASE("Writer: events_out counts only events that reached the file, on a full disk too") {
  // /dev/full: every write fails with ENOSPC, like a full disk.
  auto w = lcmx::eventlog::Writer::open("/dev/full", lcmx::eventlog::OpenMode::overwrite);
  const std::vector<std::byte> small(100, std::byte{1}), big(1 << 20, std::byte{2});
  w.write(1, "SMALL", small);  // buffered: accepted, not out yet
  w.write(2, "SMALL", small);
  CHECK(w.events() == 2);
  CHECK(w.events_out() == 0);
  CHECK_THROWS_AS(w.flush(), lcmx::eventlog::Error);
  CHECK(w.events_out() == 0);
  CHECK_THROWS_AS(w.write(3, "BIG", big), lcmx::eventlog::Error);  // written directly, fails
  CHECK(w.events_out() == 0);

  TmpDir d;
  auto w2 = lcmx::eventlog::Writer::open(d.file("ok.lcmlog"), lcmx::eventlog::OpenMode::overwrite);
  w2.write(1, "SMALL", small);
  CHECK(w2.events_out() == 0);
  w2.write(2, "BIG", big);  // flushes the small one, then writes itself
  CHECK(w2.events_out() == 2);
  w2.write(3, "SMALL", small);
  w2.flush();
  CHECK(w2.events_out() == 3);
}
