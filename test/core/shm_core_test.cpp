// Core's use of the shm API (issue 10): torn samples (ReadSample::intact), drops when every
// slot is pinned (Writer::dropped -> PublisherStats), the executor's wait bounded by
// Reader::retry_at. The publisher runs in a forked child (before this process creates its
// Runtime), driven step by step through pipes; the subscribers run here.
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <catch2/catch.hpp>
#include <condition_variable>
#include <cstring>
#include <dirent.h>
#include <mutex>
#include <thread>

#include "core_support.hpp"
#include "lcmx/core.hpp"
#include "lcmx/shm/segment.hpp"

namespace {

using namespace std::chrono_literals;
using Clock = std::chrono::steady_clock;
using lcmx::core_test::eventually;

// The publisher child and this process share one group; a 2 s lease outlasts the child's
// stepwise pauses.
lcmx::RuntimeOptions shm_test_options() {
  auto o = lcmx::core_test::test_options();
  o.lease = 2000ms;
  return o;
}

constexpr auto kWait = 10000ms;  // eventually()'s deadline here

// A publisher process: publishes message k (8 bytes, k) on `channel` each time it reads a
// byte 'p' from its command pipe ('g': 16 KiB starting with k, so its segment grows); 's' writes "published shm_dropped\n" to its report pipe;
// 'q' (or EOF) ends it. Started before the parent's Runtime exists.
struct PublisherChild {
  pid_t pid = -1;
  int cmd = -1;     // parent writes
  int report = -1;  // parent reads

  PublisherChild(const lcmx::RuntimeOptions& o, const std::string& channel, std::size_t subscribers) {
    int c[2], r[2];
    REQUIRE(::pipe(c) == 0);
    REQUIRE(::pipe(r) == 0);
    pid = ::fork();
    REQUIRE(pid >= 0);
    if (pid == 0) {
      ::close(c[1]);
      ::close(r[0]);
      ::alarm(60);  // watchdog
      int code = 0;
      try {
        auto rt = lcmx::Runtime::create(o);
        auto node = rt.create_node("pub");
        auto pub = node.advertise_raw(channel);  // default options: 8 slots
        if (!pub.wait_for_subscribers(subscribers, 20000ms)) _exit(2);
        const char ready = 'r';
        if (::write(r[1], &ready, 1) != 1) _exit(3);
        std::uint64_t k = 0;
        char ch;
        while (::read(c[0], &ch, 1) == 1 && ch != 'q') {
          if (ch == 'p' || ch == 'g') {  // 'g': 16 KiB, past the first slot size (growth)
            std::vector<std::byte> b(ch == 'p' ? 8 : 16384);
            std::memcpy(b.data(), &k, 8);
            pub.publish(b);  // must never throw, whatever the readers pin
            ++k;
          } else if (ch == 's') {
            const auto s = pub.stats();
            const std::string line = std::to_string(s.published) + " " + std::to_string(s.shm_dropped) + "\n";
            if (::write(r[1], line.data(), line.size()) != static_cast<ssize_t>(line.size())) _exit(3);
          }
        }
      } catch (...) {
        code = 4;
      }
      _exit(code);
    }
    ::close(c[0]);
    ::close(r[1]);
    cmd = c[1];
    report = r[0];
  }
  ~PublisherChild() {
    if (cmd >= 0) ::close(cmd);  // EOF: the child ends
    if (pid > 0) {
      int st = 0;
      const auto end = Clock::now() + 5s;
      while (::waitpid(pid, &st, WNOHANG) == 0) {
        if (Clock::now() > end) {
          ::kill(pid, SIGKILL);
          ::waitpid(pid, &st, 0);
          break;
        }
        std::this_thread::sleep_for(2ms);
      }
    }
    if (report >= 0) ::close(report);
  }
  void send(char ch) { REQUIRE(::write(cmd, &ch, 1) == 1); }
  // Reads one line (blocking; the child's alarm bounds it).
  std::string line() {
    std::string s;
    char ch;
    while (::read(report, &ch, 1) == 1 && ch != '\n') s += ch;
    return s;
  }
  bool ready() { char ch = 0; return ::read(report, &ch, 1) == 1 && ch == 'r'; }
  // The child's segment files ("lcmx_<host>_<pid>n<pidns>_...", shm::process_tag).
  std::vector<std::string> segments() const {
    std::vector<std::string> out;
    const std::string mid = "_" + std::to_string(pid) + "n";
    if (DIR* d = ::opendir("/dev/shm")) {
      while (const dirent* e = ::readdir(d)) {
        const std::string n = e->d_name;
        if (n.rfind("lcmx_", 0) == 0 && n.find(mid) != std::string::npos) out.push_back(n);
      }
      ::closedir(d);
    }
    return out;
  }
};

std::uint64_t value_of(const lcmx::RawMessage& m) {
  std::uint64_t k = ~0ull;
  if (m.data.size() >= 8) std::memcpy(&k, m.data.data(), 8);
  return k;
}

}  // namespace

TEST_CASE("9 lagging RawSubscribers pin every slot: publish() never throws and drops are counted on both sides",
          "[core][shm]") {
  const auto o = shm_test_options();
  const std::string channel = "PINNED_" + std::to_string(::getpid());
  constexpr int kReaders = 9, kMessages = 20;
  PublisherChild child(o, channel, kReaders);
  auto rt = lcmx::Runtime::create(o);
  std::mutex mu;
  std::condition_variable cv;
  bool release = false;
  std::atomic<int> blocked{0};
  std::vector<lcmx::Node> nodes;
  std::vector<lcmx::RawSubscriber> subs;
  for (int i = 0; i < kReaders; ++i) {
    nodes.push_back(rt.create_node("reader" + std::to_string(i)));
    // Reader i holds (pins) the first message >= i in its callback until released.
    subs.push_back(nodes.back().subscribe_raw(channel, [&, i, held = false](const lcmx::RawMessage& m) mutable {
      if (held || value_of(m) < static_cast<std::uint64_t>(i)) return;
      held = true;
      ++blocked;
      std::unique_lock lock(mu);
      cv.wait_for(lock, 20s, [&] { return release; });
    }));
  }
  struct Release {  // every exit path frees the executor threads
    std::mutex& mu;
    std::condition_variable& cv;
    bool& release;
    ~Release() {
      { std::lock_guard l(mu); release = true; }
      cv.notify_all();
    }
  } releaser{mu, cv, release};
  REQUIRE(child.ready());
  // Messages 0..7 go to the 8 slots and are each held by one reader (reader 8 waits for a
  // message >= 8); then every slot is pinned and messages 8.. are dropped.
  for (int k = 0; k < kMessages; ++k) {
    child.send('p');
    if (k < 8) REQUIRE(eventually([&] { return blocked.load() == k + 1; }, kWait));
  }
  child.send('s');
  const auto line = child.line();
  std::uint64_t published = 0, dropped = 0;
  REQUIRE(std::sscanf(line.c_str(), "%lu %lu", &published, &dropped) == 2);
  CHECK(published == static_cast<std::uint64_t>(kMessages));
  CHECK(dropped == static_cast<std::uint64_t>(kMessages - 8));
  {
    std::lock_guard l(mu);
    release = true;
  }
  cv.notify_all();
  // Each reader counts every message it never got: at least those the writer dropped (a
  // reader held back past the ring also skips what the dropped ones pushed out of it).
  for (auto& s : subs) {
    CHECK(eventually([&] {
      const auto st = s.stats();
      return st.delivered + st.drops == static_cast<std::uint64_t>(kMessages);
    }, kWait));
    const auto st = s.stats();
    INFO("delivered " << st.delivered << " drops " << st.drops);
    CHECK(st.drops >= dropped);
  }
  child.send('q');
}

TEST_CASE("a raw shm sample whose segment is truncated during its callback is counted as a drop",
          "[core][shm]") {
  const auto o = shm_test_options();
  const std::string channel = "TORN_" + std::to_string(::getpid());
  PublisherChild child(o, channel, 1);
  auto rt = lcmx::Runtime::create(o);
  auto node = rt.create_node("reader");
  std::atomic<int> got{0};
  std::atomic<int> truncated{0};
  auto sub = node.subscribe_raw(channel, [&](const lcmx::RawMessage&) {
    // A hostile (or buggy) process with write access truncates the file under our view.
    // `got` is counted after it, so the test reads `truncated` only once it is final.
    if (got.load() == 0)
      for (const auto& n : child.segments())
        if (::truncate(("/dev/shm/" + n).c_str(), 0) == 0) ++truncated;
    ++got;
  });
  REQUIRE(child.ready());
  child.send('p');
  REQUIRE(eventually([&] { return got.load() == 1; }, kWait));
  REQUIRE(truncated.load() > 0);
  // The view the callback had may have been torn: not silent, a drop of its pair.
  CHECK(eventually([&] { return sub.stats().drops == 1; }, 3000ms));
  CHECK(sub.stats().delivered == 1);
  child.send('q');
}

TEST_CASE("a reader whose generation follow failed delivers later without a commit waking it",
          "[core][shm][executor]") {
  const auto o = shm_test_options();
  const std::string channel = "RETRY_" + std::to_string(::getpid());
  PublisherChild child(o, channel, 1);
  auto rt = lcmx::Runtime::create(o);
  lcmx::NodeOptions manual;
  manual.executor.kind = lcmx::ExecutorKind::manual;
  auto node = rt.create_node("reader", manual);
  std::vector<std::uint64_t> got;
  auto sub = node.subscribe_raw(channel, [&](const lcmx::RawMessage& m) { got.push_back(value_of(m)); });
  REQUIRE(child.ready());
  child.send('p');
  for (int i = 0; i < 100 && got.empty(); ++i) node.spin_once(100ms);
  REQUIRE(got.size() == 1);
  // Message 1 moves the publisher to generation 1; before our reader follows, generation 1's
  // subscriber table is filled, so the follow fails and the reader backs off (100 ms).
  child.send('g');
  // Generation 1's file shows up before the publisher has finished writing its header (the
  // magic is stored last): until then opening it says `corrupt`, so wait for a first Reader.
  std::string g1;
  std::vector<lcmx::shm::Reader> fill;
  REQUIRE(eventually([&] {
    for (const auto& n : child.segments())
      if (n.size() > 3 && n.compare(n.size() - 3, 3, "_g1") == 0) g1 = n;
    if (g1.empty()) return false;
    try {
      fill.push_back(lcmx::shm::Reader::open(g1));
      return true;
    } catch (const lcmx::shm::Error& e) {
      if (e.code() != lcmx::shm::Errc::corrupt) throw;
      return false;
    }
  }, kWait));
  for (int i = 0; i < 4096; ++i) {
    try {
      fill.push_back(lcmx::shm::Reader::open(g1));
    } catch (const lcmx::shm::Error& e) {
      REQUIRE(e.code() == lcmx::shm::Errc::no_subscriber_slot);
      break;
    }
  }
  REQUIRE(!fill.empty());
  // The follow fails (the executor logs it) and nothing is delivered.
  for (int i = 0; i < 20 && got.size() == 1; ++i) node.spin_once(5ms);
  CHECK(got.size() == 1);
  fill.clear();  // room again; no commit follows to wake the reader
  const auto start = Clock::now();
  const auto end = start + 5s;
  while (got.size() < 2 && Clock::now() < end) node.spin_once(5s);
  const auto took = std::chrono::duration_cast<std::chrono::milliseconds>(Clock::now() - start);
  std::fprintf(stderr, "failed follow -> delivered without a commit: %lld ms\n",
               static_cast<long long>(took.count()));
  REQUIRE(got.size() == 2);
  CHECK(got[1] == 1);
  // Bounded by Reader::retry_at (100 ms back-off), not by the executor's 1 s wait.
  CHECK(took < 600ms);
  child.send('q');
}

TEST_CASE("RawMessage::retain keeps shm samples zero-copy past the callback, copies beyond the pins, outlives the subscriber and publisher",
          "[core][shm][retain]") {
  const auto o = shm_test_options();
  const std::string channel = "RETAIN_" + std::to_string(::getpid());
  PublisherChild child(o, channel, 1);
  auto rt = lcmx::Runtime::create(o);
  auto node = rt.create_node("holder");
  std::mutex mu;
  std::vector<lcmx::RetainedBytes> kept;
  int same = 0;  // checked here, not in the callback (Catch is not thread-safe)
  auto sub = node.subscribe_raw(channel, [&](const lcmx::RawMessage& m) {
    auto r = m.retain();
    auto again = m.retain();  // same bytes, no second pin
    std::lock_guard lock(mu);
    if (again.data.data() == r.data.data() && again.zero_copy == r.zero_copy) ++same;
    kept.push_back(std::move(r));
  });
  const auto count = [&] {
    std::lock_guard lock(mu);
    return kept.size();
  };
  REQUIRE(child.ready());
  constexpr std::size_t kMax = lcmx::shm::Reader::kMaxDetached;
  // One at a time: kMaxDetached zero-copy holds, then copies (the subscriber keeps
  // receiving: one pin always stays for take()).
  for (std::size_t k = 0; k < kMax + 2; ++k) {
    child.send('p');
    REQUIRE(eventually([&] { return count() == k + 1; }, kWait));
  }
  {
    std::lock_guard lock(mu);
    for (std::size_t k = 0; k < kept.size(); ++k) {
      INFO("message " << k);
      CHECK(kept[k].zero_copy == (k < kMax));
      REQUIRE(kept[k].data.size() == 8);
      std::uint64_t v = ~0ull;
      std::memcpy(&v, kept[k].data.data(), 8);
      CHECK(v == k);
    }
    // Released on another thread (as ZeroMQ's I/O thread does): the pin comes back.
    std::thread([r = std::move(kept[0])]() mutable { lcmx::RetainedBytes x = std::move(r); }).join();
  }
  child.send('p');
  REQUIRE(eventually([&] { return count() == kMax + 3; }, kWait));
  {
    std::lock_guard lock(mu);
    CHECK(kept.back().zero_copy);
    CHECK(same == static_cast<int>(kept.size()));
  }
  child.send('s');
  std::uint64_t published = 0, dropped = 0;
  REQUIRE(std::sscanf(child.line().c_str(), "%lu %lu", &published, &dropped) == 2);
  CHECK(published == kMax + 3);
  CHECK(dropped == 0);  // 8 slots, at most kMaxPins pinned by us
  CHECK(sub.stats().drops == 0);
  // The subscriber and then the publisher go away; what was retained stays readable.
  sub.reset();
  child.send('q');
  REQUIRE(eventually([&] {
    int st = 0;
    return ::waitpid(child.pid, &st, WNOHANG) == child.pid;
  }, kWait));
  child.pid = -1;
  std::lock_guard lock(mu);
  for (std::size_t k = 1; k < kept.size(); ++k) {
    std::uint64_t v = ~0ull;
    std::memcpy(&v, kept[k].data.data(), 8);
    CHECK(v == k);
  }
  kept.clear();  // the last holders unmap and deregister
}
