// Helpers for lcmx's multi-process integration tests (STYLE.md "Tests"):
//  - Session: one per TEST_CASE. Its own discovery group (unique per pid + test index), a
//    watchdog (overall deadline: kills every child, then aborts), and RAII cleanup that kills
//    and reaps every child and removes the /dev/shm segments of every process it started.
//  - Child: a real process (posix_spawn) with stdout (and optionally stderr) on a pipe and
//    stdin on a pipe; read lines with deadlines, never sleep to synchronise.
//  - Netns: a network namespace with lo up and a multicast route, deleted on every exit path.
#pragma once

#include <catch2/catch.hpp>
#include <dirent.h>
#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <spawn.h>
#include <sys/mman.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <stdexcept>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "lcmx/test/skip.hpp"
#include "lcmx/test/tmp_dir.hpp"

extern char** environ;

namespace lcmx::it {

using namespace std::chrono_literals;
using Clock = std::chrono::steady_clock;
using ms = std::chrono::milliseconds;

// ---- unique names ----

// A discovery group of its own for test `index` of this process: never LCM's default group.
// Host-local mode (no iface=): inside a test's network namespace. Tests in the root namespace
// add "&iface=lo" (Session does), so they never join a group on the machine's real interface.
// `index` < 256: (pid, index) and (pid + 1, index - 256) would share a group, and the two test
// processes ctest starts together often have consecutive pids.
inline std::string unique_url(int index) {
  if (index < 0 || index >= 256) throw std::invalid_argument("unique_url: test index out of [0, 256)");
  const unsigned h = static_cast<unsigned>(::getpid()) * 256u + static_cast<unsigned>(index);
  unsigned a = 1 + (h / 250u) % 250u, b = 1 + h % 250u;
  if (a == 76 && b == 67) b = 68;
  const unsigned port = 20000 + h % 40000u;
  return "udpm://239.255." + std::to_string(a) + "." + std::to_string(b) + ":" + std::to_string(port) + "?ttl=0";
}

inline std::string unique_channel(const std::string& base, int index) {
  return "IT_" + base + "_" + std::to_string(::getpid()) + "_" + std::to_string(index);
}

// ---- shared memory files ----

inline bool shm_exists(const std::string& name) { return ::access(("/dev/shm/" + name).c_str(), F_OK) == 0; }

// lcmx segment names: "lcmx_<host hex>_<pid>n<pidns hex>_<endpoint>_g<N>" (shm::process_tag).
// Those created by `pid` (in any pid namespace).
inline std::vector<std::string> shm_segments_of(pid_t pid) {
  std::vector<std::string> out;
  const std::string mid = "_" + std::to_string(pid) + "n";
  if (DIR* d = ::opendir("/dev/shm")) {
    while (const dirent* e = ::readdir(d)) {
      const std::string n = e->d_name;
      if (n.rfind("lcmx_", 0) != 0) continue;
      const auto us = n.find('_', 5);  // after the host id
      if (us != std::string::npos && n.compare(us, mid.size(), mid) == 0) out.push_back(n);
    }
    ::closedir(d);
  }
  return out;
}

inline void remove_shm_of(pid_t pid) {
  for (const auto& n : shm_segments_of(pid)) ::shm_unlink(("/" + n).c_str());
}

// ---- waiting ----

// Polls `pred` until it holds or the deadline passes (polling a condition, not sleeping to
// synchronise). Returns whether it held.
inline bool wait_until(const std::function<bool()>& pred, ms timeout, ms step = 5ms) {
  const auto deadline = Clock::now() + timeout;
  for (;;) {
    if (pred()) return true;
    if (Clock::now() >= deadline) return false;
    std::this_thread::sleep_for(step);
  }
}

inline bool contains(const std::string& s, const std::string& what) { return s.find(what) != std::string::npos; }

// LCM's default URL: what stock LCM programs use when LCM_DEFAULT_URL is not set.
inline const std::string kLcmDefaultUrl = "udpm://239.255.76.67:7667?ttl=0";

// A fresh /tmp/lcmx_it_* directory (mode 0755: stock LCM tools and peers write into it too),
// removed when the test leaves its scope.
struct TmpDir : lcmx::test::TmpDir {
  TmpDir() : lcmx::test::TmpDir("lcmx_it", 0755) {}
};

inline bool contains_any(const std::string& s, std::initializer_list<const char*> words) {
  for (const char* w : words)
    if (s.find(w) != std::string::npos) return true;
  return false;
}

// ---- JSON lines of the lcmx tool (--json) ----

// The last line of `text` that starts with '{' (a --json summary).
inline std::string json_line(const std::string& text) {
  std::string last;
  std::istringstream in(text);
  for (std::string l; std::getline(in, l);)
    if (!l.empty() && l[0] == '{') last = l;
  return last;
}

// A number field "key":N of a flat JSON line (its first occurrence); fails the test if absent.
inline double json_num(const std::string& j, const std::string& key) {
  const auto p = j.find("\"" + key + "\":");
  if (p == std::string::npos) FAIL("no " << key << " in " << j);
  return std::stod(j.substr(p + key.size() + 3));
}

// A test that needs a network namespace it could not create: skipped (LCMX_SKIP: CTest shows
// "Skipped") where namespaces are not permitted, failed on any other error. `ns` has ok() and
// error().
#define REQUIRE_NETNS_OR_SKIP(ns)                                                                 \
  if (!(ns).ok()) {                                                                               \
    if (::lcmx::it::contains_any((ns).error(), {"Operation not permitted", "Permission denied"})) \
      LCMX_SKIP("cannot create a network namespace here: " << (ns).error());                     \
    FAIL("ip netns add failed: " << (ns).error());                                                \
  }

// ---- key=value lines ----

inline std::map<std::string, std::string> parse_kv(const std::string& line) {
  std::map<std::string, std::string> kv;
  std::istringstream in(line);
  std::string tok;
  while (in >> tok)
    if (const auto eq = tok.find('='); eq != std::string::npos) kv[tok.substr(0, eq)] = tok.substr(eq + 1);
  return kv;
}

struct Summary {
  std::map<std::string, std::string> kv;
  std::vector<std::string> errors;
  long long num(const std::string& k) const {
    auto it = kv.find(k);
    if (it == kv.end()) FAIL("summary has no field " << k);
    return std::stoll(it->second);
  }
  std::string str(const std::string& k) const {
    auto it = kv.find(k);
    return it == kv.end() ? std::string() : it->second;
  }
};

// ---- child processes ----

class Child {
 public:
  Child(const std::vector<std::string>& argv, const std::vector<std::string>& env, bool merge_stderr = false)
      : argv0_(argv.at(0)) {
    int out[2], in[2];
    if (::pipe2(out, O_CLOEXEC) != 0 || ::pipe2(in, O_CLOEXEC) != 0) throw std::runtime_error("pipe2 failed");
    posix_spawn_file_actions_t fa;
    posix_spawn_file_actions_init(&fa);
    posix_spawn_file_actions_adddup2(&fa, out[1], STDOUT_FILENO);
    if (merge_stderr) posix_spawn_file_actions_adddup2(&fa, out[1], STDERR_FILENO);
    posix_spawn_file_actions_adddup2(&fa, in[0], STDIN_FILENO);
    std::vector<char*> args;
    for (const auto& a : argv) args.push_back(const_cast<char*>(a.c_str()));
    args.push_back(nullptr);
    // Environment: ours, then `env` in order: "K=V" sets K (the last one wins), "K" unsets it.
    std::vector<std::pair<std::string, std::string>> vars;
    auto set = [&](const std::string& e) {
      const auto eq = e.find('=');
      const std::string key = e.substr(0, eq);
      std::erase_if(vars, [&](const auto& kv) { return kv.first == key; });
      if (eq != std::string::npos) vars.emplace_back(key, e);
    };
    for (char** p = environ; *p; ++p) set(*p);
    for (const auto& e : env) set(e);
    std::vector<std::string> envs;
    for (auto& kv : vars) envs.push_back(kv.second);
    std::vector<char*> envp;
    for (auto& e : envs) envp.push_back(e.data());
    envp.push_back(nullptr);
    const int rc = ::posix_spawnp(&pid_, args[0], &fa, nullptr, args.data(), envp.data());
    posix_spawn_file_actions_destroy(&fa);
    ::close(out[1]);
    ::close(in[0]);
    if (rc != 0) {
      ::close(out[0]);
      ::close(in[1]);
      pid_ = -1;
      throw std::runtime_error("cannot start " + argv[0] + ": " + std::strerror(rc));
    }
    out_ = out[0];
    in_ = in[1];
  }
  Child(const Child&) = delete;
  Child& operator=(const Child&) = delete;
  // A child still running is stopped as its user would stop it, so that it removes its
  // registry slot, state file and segments: its stdin closed (the test peers that wait for
  // that end then) and 100 ms to exit, then SIGTERM (SIGCONT for a stopped one) and a second,
  // then SIGKILL.
  ~Child() {
    if (pid_ > 0 && in_ >= 0) {
      ::close(in_);
      in_ = -1;
      exited_within(100ms);
    }
    if (pid_ > 0) {
      ::kill(pid_, SIGTERM);
      ::kill(pid_, SIGCONT);
      exited_within(1000ms);
    }
    kill_and_reap();
    if (out_ >= 0) ::close(out_);
    if (in_ >= 0) ::close(in_);
  }

  // Next stdout line, or nullopt on EOF or when the deadline passes. Every line is kept.
  std::optional<std::string> read_line(ms timeout = 10000ms) {
    const auto deadline = Clock::now() + timeout;
    for (;;) {
      if (const auto nl = buf_.find('\n'); nl != std::string::npos) {
        std::string line = buf_.substr(0, nl);
        buf_.erase(0, nl + 1);
        history_.push_back(line);
        return line;
      }
      if (eof_) return std::nullopt;
      const auto left = std::chrono::duration_cast<ms>(deadline - Clock::now());
      pollfd p{out_, POLLIN, 0};
      // A zero timeout still reads what is already there.
      if (::poll(&p, 1, static_cast<int>(std::max<long long>(left.count(), 0))) <= 0) {
        if (left.count() <= 0) return std::nullopt;
        continue;
      }
      char chunk[8192];
      const ssize_t n = ::read(out_, chunk, sizeof chunk);
      if (n <= 0) eof_ = true;
      else buf_.append(chunk, static_cast<std::size_t>(n));
    }
  }

  // Reads lines until one starts with `prefix` (returned) or EOF/deadline (nullopt).
  std::optional<std::string> expect(const std::string& prefix, ms timeout = 10000ms) {
    const auto deadline = Clock::now() + timeout;
    for (;;) {
      auto line = read_line(std::chrono::duration_cast<ms>(deadline - Clock::now()));
      if (!line) return std::nullopt;
      if (line->rfind(prefix, 0) == 0) return line;
      if (line->rfind("FATAL", 0) == 0 || line->rfind("TIMEOUT", 0) == 0) return std::nullopt;
    }
  }

  // "status"/"quit" on stdin, then the SUMMARY lines up to "END".
  std::vector<Summary> summaries(const std::string& command, ms timeout = 10000ms) {
    if (!command.empty()) send(command);
    return read_summaries(timeout);
  }
  std::vector<Summary> read_summaries(ms timeout = 10000ms) {
    std::vector<Summary> out;
    const auto deadline = Clock::now() + timeout;
    for (;;) {
      auto line = read_line(std::chrono::duration_cast<ms>(deadline - Clock::now()));
      if (!line) break;
      if (line->rfind("SUMMARY", 0) == 0) out.push_back({parse_kv(*line), {}});
      else if (line->rfind("ERROR ", 0) == 0 && !out.empty()) out.back().errors.push_back(line->substr(6));
      else if (*line == "END") return out;
    }
    FAIL("no complete summary from " << argv0_ << " (pid " << pid_ << "); output:\n" << output());
    return out;
  }

  // Whether any line read so far starts with `prefix`.
  bool seen(const std::string& prefix) const {
    for (const auto& l : history_)
      if (l.rfind(prefix, 0) == 0) return true;
    return false;
  }
  // Reads lines until `prefix` was seen (now or before) or the deadline passes.
  bool wait_seen(const std::string& prefix, ms timeout) {
    if (seen(prefix)) return true;
    return expect(prefix, timeout).has_value();
  }
  std::string output() const {
    std::string s;
    for (const auto& l : history_) s += "  | " + l + "\n";
    return s;
  }

  std::string text() const {
    std::string s;
    for (const auto& l : history_) s += l + "\n";
    return s;
  }

  void send(const std::string& line) {
    const std::string s = line + "\n";
    [[maybe_unused]] auto n = ::write(in_, s.data(), s.size());
  }
  void signal(int sig) {
    if (pid_ > 0) ::kill(pid_, sig);
  }
  // SIGKILL, reaped at once: the process is dead (not a zombie) when this returns.
  void kill9() { kill_and_reap(); }

  // Waits for exit up to the deadline (then SIGKILL); the exit code, or -signal.
  int wait(ms timeout = 10000ms) {
    const auto deadline = Clock::now() + timeout;
    int st = 0;
    for (;;) {
      while (read_line(0ms)) {
      }
      const pid_t r = ::waitpid(pid_, &st, WNOHANG);
      if (r == pid_) break;
      if (Clock::now() >= deadline) {
        ::kill(pid_, SIGKILL);
        ::waitpid(pid_, &st, 0);
        break;
      }
      pollfd p{out_, POLLIN, 0};
      ::poll(&p, 1, eof_ ? 5 : 50);  // wakes on output, bounded by the deadline
    }
    while (read_line(0ms)) {
    }
    pid_ = -1;
    return WIFEXITED(st) ? WEXITSTATUS(st) : -WTERMSIG(st);
  }
  // Whether read_line() has seen the end of stdout (the child closed it, normally by exiting).
  // A read_line() that returned nullopt may also have timed out: ask this, not the clock.
  bool eof() const { return eof_; }
  bool running() const { return pid_ > 0; }
  pid_t pid() const { return pid_; }
  pid_t started_pid() const { return started_pid_; }

 private:
  // Reaps the child if it exits within `timeout` (pid_ then -1), draining its output meanwhile so
  // that a child blocked on a full pipe can exit.
  void exited_within(ms timeout) {
    const auto deadline = Clock::now() + timeout;
    int st = 0;
    for (int guard = 0; guard < 10000 && Clock::now() < deadline; ++guard) {
      const pid_t r = ::waitpid(pid_, &st, WNOHANG);
      if (r == pid_ || (r < 0 && errno != EINTR)) {
        pid_ = -1;
        return;
      }
      pollfd p{out_, POLLIN, 0};
      if (eof_ || out_ < 0) ::poll(nullptr, 0, 5);
      else if (::poll(&p, 1, 5) > 0) read_line(0ms);
    }
  }
  void kill_and_reap() {
    if (pid_ > 0) {
      ::kill(pid_, SIGKILL);
      int st = 0;
      ::waitpid(pid_, &st, 0);
      pid_ = -1;
    }
  }
  std::string argv0_;
  pid_t pid_ = -1;
  pid_t started_pid_ = -1;

 public:
  void set_started() { started_pid_ = pid_; }

 private:
  int out_ = -1, in_ = -1;
  std::string buf_;
  bool eof_ = false;
  std::vector<std::string> history_;
};

// The summary of `channel` in a list of summaries (FAIL if absent).
#ifdef LCMX_TMUX
// A tmux server of this test's own (-L socket), killed at the end whatever happens: terminal
// programs are tested in it (send-keys, capture-pane).
class Tmux {
 public:
  explicit Tmux(std::string sock) : sock_(std::move(sock)) {}
  ~Tmux() { run({"kill-server"}); }
  struct Result {
    int rc;
    std::string out;
  };
  Result run(std::vector<std::string> args) const {
    args.insert(args.begin(), {LCMX_TMUX, "-L", sock_});
    Child c(args, {}, true);
    const int rc = c.wait(5000ms);
    return {rc, c.text()};
  }
  std::string pane(const std::string& session) const { return run({"capture-pane", "-p", "-t", session}).out; }
  bool keys(const std::string& session, std::vector<std::string> keys) const {
    keys.insert(keys.begin(), {"send-keys", "-t", session});
    return run(keys).rc == 0;
  }
  // Polls the screen until `pred` holds (deadline).
  bool wait_screen(const std::string& session, const std::function<bool(const std::string&)>& pred,
                   ms timeout = 10000ms) const {
    return wait_until([&] { return pred(pane(session)); }, timeout, 50ms);
  }

 private:
  std::string sock_;
};
#endif

// Reads lines of `c` until a JSON line ('{...') for which `pred` holds (returned), or the
// deadline passes (nullopt).
inline std::optional<std::string> json_until(Child& c, const std::function<bool(const std::string&)>& pred,
                                             ms timeout) {
  const auto deadline = Clock::now() + timeout;
  for (;;) {
    const auto left = std::chrono::duration_cast<ms>(deadline - Clock::now());
    if (left.count() <= 0) return std::nullopt;
    auto line = c.read_line(left);
    if (!line) return std::nullopt;
    if (!line->empty() && (*line)[0] == '{' && pred(*line)) return line;
  }
}

inline Summary of(const std::vector<Summary>& all, const std::string& channel) {
  for (const auto& s : all)
    if (s.str("channel") == channel) return s;
  FAIL("no summary for channel " << channel);
  return {};
}

// Asks a subscriber peer for its status until `pred` holds for `channel` (deadline).
inline std::optional<Summary> poll_sub(Child& sub, const std::string& channel,
                                       const std::function<bool(const Summary&)>& pred, ms timeout) {
  const auto deadline = Clock::now() + timeout;
  for (;;) {
    auto last = of(sub.summaries("status"), channel);
    if (pred(last)) return last;
    if (Clock::now() >= deadline) {
      UNSCOPED_INFO("last status of " << channel << ": received=" << last.str("received")
                                      << " publishers=" << last.str("publishers")
                                      << " drops=" << last.str("drops") << " paths=" << last.str("paths"));
      return std::nullopt;
    }
    std::this_thread::sleep_for(20ms);  // polling interval of a condition with a deadline
  }
}

// Asks a publisher peer how many messages it has published.
inline long long published(Child& pub) {
  pub.send("status");
  auto line = pub.expect("STATUS", 5000ms);
  REQUIRE(line);
  return std::stoll(parse_kv(*line).at("published"));
}

// Overall deadline for a test: kills every registered child, then aborts the test process.
class Watchdog {
 public:
  Watchdog(ms timeout, std::function<void()> on_fire) {
    thread_ = std::thread([this, timeout, on_fire = std::move(on_fire)] {
      std::unique_lock lock(mu_);
      if (cv_.wait_for(lock, timeout, [&] { return done_; })) return;
      std::fprintf(stderr, "WATCHDOG: test exceeded %lld ms: killing its children\n",
                   static_cast<long long>(timeout.count()));
      on_fire();
      if (cv_.wait_for(lock, 5s, [&] { return done_; })) return;
      std::fprintf(stderr, "WATCHDOG: test still stuck 5 s later: abort\n");
      std::abort();
    });
  }
  ~Watchdog() {
    {
      std::lock_guard lock(mu_);
      done_ = true;
    }
    cv_.notify_all();
    thread_.join();
  }

 private:
  std::mutex mu_;
  std::condition_variable cv_;
  bool done_ = false;
  std::thread thread_;
};

// One per TEST_CASE: group, environment for children, watchdog, cleanup.
class Session {
 public:
  explicit Session(int index, ms timeout = 30000ms, ms beacon = 100ms, ms lease = 600ms)
      : index(index), url(unique_url(index) + "&iface=lo"), beacon_ms(beacon), lease_ms(lease),
        watchdog_(timeout, [this] { kill_all(); }) {
    ::setenv("LCMX_DISCOVERY_URL", url.c_str(), 1);
    ::setenv("LCMX_BEACON_PERIOD_MS", std::to_string(beacon.count()).c_str(), 1);
    ::setenv("LCMX_LEASE_MS", std::to_string(lease.count()).c_str(), 1);
  }
  Session(const Session&) = delete;
  Session& operator=(const Session&) = delete;
  ~Session() {
    std::vector<pid_t> pids;
    {
      std::lock_guard lock(mu_);
      for (auto& c : children_) pids.push_back(c->started_pid());
      children_.clear();  // kills and reaps
    }
    for (auto pid : pids) remove_shm_of(pid);
    for (auto pid : extra_pids_) remove_shm_of(pid);
    remove_shm_of(::getpid());
  }

  std::vector<std::string> env(ms beacon, ms lease) const {
    return {"LCMX_DISCOVERY_URL=" + url, "LCMX_BEACON_PERIOD_MS=" + std::to_string(beacon.count()),
            "LCMX_LEASE_MS=" + std::to_string(lease.count()), "SPDLOG_LEVEL=warn"};
  }

  // Starts a process; `extra_env` entries override the session's.
  Child& spawn(std::vector<std::string> argv, std::vector<std::string> extra_env = {}, bool merge_stderr = false) {
    auto e = env(beacon_ms, lease_ms);
    for (auto& x : extra_env) e.push_back(std::move(x));
    auto c = std::make_unique<Child>(argv, e, merge_stderr);
    c->set_started();
    std::lock_guard lock(mu_);
    children_.push_back(std::move(c));
    return *children_.back();
  }

  // The test peer with `args`, and --timeout-ms bounded by the session's deadline.
  Child& peer(std::vector<std::string> args, std::vector<std::string> extra_env = {}) {
    args.insert(args.begin(), LCMX_TEST_PEER);
    args.push_back("--timeout-ms");
    args.push_back("60000");
    return spawn(std::move(args), std::move(extra_env));
  }

  // Runs a command to completion; merged stdout+stderr and the exit code.
  struct Result {
    int rc;
    std::string out;
  };
  Result run(std::vector<std::string> argv, std::vector<std::string> extra_env = {}, ms timeout = 15000ms) {
    Child& c = spawn(std::move(argv), std::move(extra_env), true);
    const int rc = c.wait(timeout);
    return {rc, c.text()};
  }

  // Marks a process whose segments this test must remove (e.g. a grandchild).
  void track_pid(pid_t p) { extra_pids_.push_back(p); }

  const int index;
  const std::string url;
  const ms beacon_ms, lease_ms;

 private:
  void kill_all() {
    std::lock_guard lock(mu_);
    for (auto& c : children_) c->signal(SIGKILL);
  }
  std::mutex mu_;
  std::vector<std::unique_ptr<Child>> children_;
  std::vector<pid_t> extra_pids_;
  Watchdog watchdog_;  // last: stopped first
};

// ---- network namespaces ----

inline int run_quiet(const std::vector<std::string>& argv) {
  Child c(argv, {}, true);
  return c.wait(10000ms);
}

// "lcmxit_<pid>_<n>" with lo up and 224.0.0.0/4 routed to lo; deleted on destruction.
// Namespaces left by dead test processes are removed first.
class Netns {
 public:
  Netns() {
    remove_stale();
    static int counter = 0;
    name_ = "lcmxit_" + std::to_string(::getpid()) + "_" + std::to_string(++counter);
    Child add({LCMX_IP, "netns", "add", name_}, {}, true);
    const int rc = add.wait(10000ms);
    if (rc != 0) {
      error_ = add.output();
      return;
    }
    created_ = true;
    if (run_quiet({LCMX_IP, "-n", name_, "link", "set", "lo", "up"}) != 0 ||
        run_quiet({LCMX_IP, "-n", name_, "route", "add", "224.0.0.0/4", "dev", "lo"}) != 0) {
      del();
      throw std::runtime_error("cannot set up lo in " + name_);
    }
  }
  Netns(const Netns&) = delete;
  Netns& operator=(const Netns&) = delete;
  ~Netns() { del(); }
  bool ok() const { return created_; }
  const std::string& error() const { return error_; }
  const std::string& name() const { return name_; }

 private:
  void del() {
    if (created_) run_quiet({LCMX_IP, "netns", "del", name_});
    created_ = false;
  }
  static void remove_stale() {
    DIR* d = ::opendir("/run/netns");
    if (d == nullptr) return;
    std::vector<std::string> stale;
    while (const dirent* e = ::readdir(d)) {
      const std::string n = e->d_name;
      if (n.rfind("lcmxit_", 0) != 0) continue;
      const auto us = n.find('_', 7);
      if (us == std::string::npos) continue;
      const pid_t pid = static_cast<pid_t>(std::atol(n.substr(7, us - 7).c_str()));
      if (pid > 0 && ::kill(pid, 0) != 0 && errno == ESRCH) stale.push_back(n);
    }
    ::closedir(d);
    for (const auto& n : stale) run_quiet({LCMX_IP, "netns", "del", n});
  }
  std::string name_, error_;
  bool created_ = false;
};

}  // namespace lcmx::it
