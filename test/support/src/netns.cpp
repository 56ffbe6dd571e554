#include "lcmx/test/netns.hpp"

#include <arpa/inet.h>
#include <dirent.h>
#include <fcntl.h>
#include <net/if.h>
#include <poll.h>
#include <spawn.h>
#include <sys/ioctl.h>
#include <sys/mount.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <cctype>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>
#include <fstream>
#include <mutex>
#include <set>
#include <sstream>
#include <stdexcept>

#include "registry.hpp"

#ifndef LCMX_TEST_IP
#define LCMX_TEST_IP "/usr/sbin/ip"
#endif
#ifndef LCMX_TEST_TC
#define LCMX_TEST_TC "/usr/sbin/tc"
#endif

extern char** environ;

namespace lcmx::test {

// ---------------------------------------------------------------------------------------------
// Registry (lock-free, fixed size: emergency_teardown() runs in a dying process).
namespace detail {
namespace {
constexpr int kMaxNs = 512;
constexpr int kMaxChildren = 1024;
constexpr std::size_t kPathLen = 96;
struct NsSlot {
  std::atomic<int> state{0};  // 0 free, 1 being written, 2 live
  char path[kPathLen]{};
};
NsSlot g_ns[kMaxNs];
std::atomic<pid_t> g_children[kMaxChildren];
}  // namespace

bool register_netns(const char* path) noexcept {
  if (std::strlen(path) >= kPathLen) return false;
  for (auto& s : g_ns) {
    int expected = 0;
    if (s.state.compare_exchange_strong(expected, 1, std::memory_order_acquire)) {
      std::strcpy(s.path, path);
      s.state.store(2, std::memory_order_release);  // pairs with the acquire in teardown
      return true;
    }
  }
  return false;
}

void unregister_netns(const char* path) noexcept {
  for (auto& s : g_ns) {
    if (s.state.load(std::memory_order_acquire) == 2 && std::strcmp(s.path, path) == 0) {
      int expected = 2;
      if (s.state.compare_exchange_strong(expected, 1, std::memory_order_acq_rel)) {
        s.path[0] = '\0';
        s.state.store(0, std::memory_order_release);
        return;
      }
    }
  }
}

bool register_child(pid_t pgid) noexcept {
  for (auto& c : g_children) {
    pid_t expected = 0;
    if (c.compare_exchange_strong(expected, pgid)) return true;
  }
  return false;
}

void unregister_child(pid_t pgid) noexcept {
  for (auto& c : g_children) {
    pid_t expected = pgid;
    if (c.compare_exchange_strong(expected, 0)) return;
  }
}
}  // namespace detail

void emergency_teardown() noexcept {
  for (auto& c : detail::g_children) {
    const pid_t p = c.load();
    if (p > 0) ::kill(-p, SIGKILL);
  }
  for (auto& s : detail::g_ns) {
    if (s.state.load(std::memory_order_acquire) != 2) continue;
    ::umount2(s.path, MNT_DETACH);
    ::unlink(s.path);
  }
}

// ---------------------------------------------------------------------------------------------
namespace {

using Clock = std::chrono::steady_clock;

std::string errno_text(const std::string& what, int e) { return what + ": " + std::strerror(e); }

// One command, optionally fed `input` on stdin (for -batch -).
struct Cmd {
  std::vector<std::string> argv;
  std::string input;
};
struct CmdResult {
  int status = -1;  // exit code, 128+signal, or -1 if it could not start
  std::string err;
};

std::string describe(const Cmd& c) {
  std::string s;
  for (const auto& a : c.argv) s += (s.empty() ? "" : " ") + a;
  if (!c.input.empty()) s += " <<EOF\n" + c.input + "EOF";
  return s;
}

// Runs the commands in parallel (posix_spawn, inheriting the calling thread's namespaces) and
// returns their results in order. Each gets at most 20 s.
std::vector<CmdResult> run_all(const std::vector<Cmd>& cmds) {
  struct Running {
    pid_t pid = -1;
    int in = -1, err = -1;
  };
  std::vector<Running> run(cmds.size());
  std::vector<CmdResult> res(cmds.size());
  for (std::size_t i = 0; i < cmds.size(); ++i) {
    int in[2], err[2];
    if (::pipe2(in, O_CLOEXEC) != 0) { res[i].err = errno_text("pipe", errno); continue; }
    if (::pipe2(err, O_CLOEXEC) != 0) {
      res[i].err = errno_text("pipe", errno);
      ::close(in[0]);
      ::close(in[1]);
      continue;
    }
    posix_spawn_file_actions_t fa;
    posix_spawn_file_actions_init(&fa);
    posix_spawn_file_actions_adddup2(&fa, in[0], 0);
    posix_spawn_file_actions_adddup2(&fa, err[1], 1);  // ip/tc stdout is noise; keep it with stderr
    posix_spawn_file_actions_adddup2(&fa, err[1], 2);
    std::vector<char*> argv;
    for (const auto& a : cmds[i].argv) argv.push_back(const_cast<char*>(a.c_str()));
    argv.push_back(nullptr);
    pid_t pid = -1;
    const int rc = ::posix_spawn(&pid, argv[0], &fa, nullptr, argv.data(), environ);
    posix_spawn_file_actions_destroy(&fa);
    ::close(in[0]);
    ::close(err[1]);
    if (rc != 0) {
      res[i].err = errno_text("posix_spawn " + cmds[i].argv[0], rc);
      ::close(in[1]);
      ::close(err[0]);
      continue;
    }
    run[i] = {pid, in[1], err[0]};
  }
  for (std::size_t i = 0; i < cmds.size(); ++i) {
    if (run[i].in < 0) continue;
    const std::string& s = cmds[i].input;
    std::size_t off = 0;
    for (int guard = 0; guard < 100000 && off < s.size(); ++guard) {
      const ssize_t n = ::write(run[i].in, s.data() + off, s.size() - off);
      if (n > 0) off += static_cast<std::size_t>(n);
      else if (errno != EINTR) break;
    }
    ::close(run[i].in);
  }
  const auto deadline = Clock::now() + std::chrono::seconds(20);
  for (std::size_t i = 0; i < cmds.size(); ++i) {
    if (run[i].pid < 0) continue;
    for (int guard = 0; guard < 100000; ++guard) {
      const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now());
      if (left.count() <= 0) {
        ::kill(run[i].pid, SIGKILL);
        res[i].err += "\n(killed after 20 s)";
        break;
      }
      pollfd p{run[i].err, POLLIN, 0};
      if (::poll(&p, 1, static_cast<int>(left.count())) <= 0) continue;
      char buf[4096];
      const ssize_t n = ::read(run[i].err, buf, sizeof buf);
      if (n > 0) res[i].err.append(buf, static_cast<std::size_t>(n));
      else if (n == 0 || errno != EINTR) break;
    }
    ::close(run[i].err);
    int st = 0;
    for (int guard = 0; guard < 100; ++guard)
      if (::waitpid(run[i].pid, &st, 0) >= 0 || errno != EINTR) break;
    res[i].status = WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
  }
  return res;
}

// Runs the commands in parallel; throws SetupError naming every one that failed.
void run_checked(const std::vector<Cmd>& cmds) {
  const auto res = run_all(cmds);
  std::string msg;
  for (std::size_t i = 0; i < cmds.size(); ++i) {
    if (res[i].status == 0) continue;
    msg += "command failed (exit " + std::to_string(res[i].status) + "): " + describe(cmds[i]) +
           "\nstderr: " + res[i].err + "\n";
  }
  if (!msg.empty()) throw SetupError(msg);
}

void write_file(const std::string& path, const std::string& value) {
  const int fd = ::open(path.c_str(), O_WRONLY | O_CLOEXEC);
  if (fd < 0) throw SetupError(errno_text("open " + path, errno));
  const ssize_t n = ::write(fd, value.data(), value.size());
  const int e = errno;
  ::close(fd);
  if (n != static_cast<ssize_t>(value.size())) throw SetupError(errno_text("write " + path, e));
}

// The first line of a file ("" if it cannot be read): one-line /proc/sys values.
std::string read_first_line(const std::string& path) {
  std::string line;
  std::ifstream in(path);
  std::getline(in, line);
  return line;
}

const std::string kAvailableCongestion = "/proc/sys/net/ipv4/tcp_available_congestion_control";

// Sets the calling thread's namespace's TCP congestion control (EmulationSpec::tcp_congestion);
// throws SetupError naming what the kernel offers when it refuses.
void set_tcp_congestion(const std::string& name, const std::string& ns) {
  const std::string path = "/proc/sys/net/ipv4/tcp_congestion_control";
  try {
    write_file(path, name);
  } catch (const SetupError& e) {
    throw SetupError("EmulationSpec::tcp_congestion '" + name + "' in " + ns + ": " + e.what() +
                     " (this kernel offers: " + read_first_line(kAvailableCongestion) + ")");
  }
}

// Some machines restrict the algorithm a network namespace may pick as its default to
// net.ipv4.tcp_allowed_congestion_control (a machine-wide list, set by root; this project's VMs
// list "reno bbr", so a namespace may not pick cubic, which Debian itself allows). Adds `name`
// to that list when the kernel offers it but the list lacks it. This only lets namespaces (and
// unprivileged sockets) select it: the machine's own default and every existing socket keep
// theirs. Idempotent, so emulations created in parallel may race on it. Must run in the
// machine's namespace (the list is global; only the initial namespace may write it). Throws
// SetupError when the list cannot be written; leaves a name the kernel does not offer to
// set_tcp_congestion, which names what it offers.
void allow_tcp_congestion(const std::string& name) {
  const auto words = [](const std::string& line) {
    std::set<std::string> out;
    std::istringstream in(line);
    for (std::string w; in >> w;) out.insert(w);
    return out;
  };
  const std::string allowed_path = "/proc/sys/net/ipv4/tcp_allowed_congestion_control";
  const std::string allowed = read_first_line(allowed_path);
  if (words(allowed).count(name) != 0) return;
  if (words(read_first_line(kAvailableCongestion)).count(name) == 0) return;
  try {
    write_file(allowed_path, allowed + " " + name);
  } catch (const SetupError& e) {
    throw SetupError("EmulationSpec::tcp_congestion '" + name + "': this machine lets namespaces pick only '" +
                     allowed + "' and adding it failed (" + e.what() +
                     "); run as root in the machine's namespace, or pass tcp_congestion = \"\" to keep the "
                     "machine's default");
  }
}

// Runs body on a fresh thread after setns(fd); throws SetupError if setns fails.
void on_thread_in(int fd, const std::function<void()>& body) {
  int err = 0;
  std::thread t([&] {
    if (::setns(fd, CLONE_NEWNET) != 0) {
      err = errno;
      return;
    }
    body();
  });
  t.join();
  if (err != 0) throw SetupError(errno_text("setns(CLONE_NEWNET)", err));
}

// ---- names ----
const std::string kNetnsDir = "/run/netns/";

struct ParsedName {
  pid_t pid;
};
// "lx<pid>_<n>_sw" or "lx<pid>_<n>_h<i>": exactly what create() makes, nothing else.
std::optional<ParsedName> parse_name(const std::string& n) {
  std::size_t i = 0;
  auto digits = [&](std::size_t& pos) {
    const std::size_t start = pos;
    while (pos < n.size() && pos - start < 10 && std::isdigit(static_cast<unsigned char>(n[pos]))) ++pos;
    return pos > start;
  };
  if (n.rfind("lx", 0) != 0) return std::nullopt;
  i = 2;
  const std::size_t pid_start = i;
  if (!digits(i) || i >= n.size() || n[i] != '_') return std::nullopt;
  const long pid = std::atol(n.substr(pid_start, i - pid_start).c_str());
  ++i;
  if (!digits(i) || i >= n.size() || n[i] != '_') return std::nullopt;
  ++i;
  const std::string rest = n.substr(i);
  if (rest != "sw") {
    if (rest.size() < 2 || rest[0] != 'h') return std::nullopt;
    std::size_t j = i + 1;
    if (!digits(j) || j != n.size()) return std::nullopt;
  }
  if (pid <= 0) return std::nullopt;
  return ParsedName{static_cast<pid_t>(pid)};
}

// SIGKILLs every process (other than this one) whose network namespace is one of `inodes`.
void kill_processes_in(const std::set<std::pair<dev_t, ino_t>>& inodes) {
  if (inodes.empty()) return;
  DIR* d = ::opendir("/proc");
  if (d == nullptr) return;
  const pid_t self = ::getpid();
  std::vector<pid_t> victims;
  for (int guard = 0; guard < 1000000; ++guard) {
    const dirent* e = ::readdir(d);
    if (e == nullptr) break;
    char* end = nullptr;
    const long pid = std::strtol(e->d_name, &end, 10);
    if (end == e->d_name || *end != '\0' || pid <= 0 || pid == self) continue;
    struct stat st {};
    const std::string p = std::string("/proc/") + e->d_name + "/ns/net";
    if (::stat(p.c_str(), &st) != 0) continue;
    if (inodes.count({st.st_dev, st.st_ino}) != 0) victims.push_back(static_cast<pid_t>(pid));
  }
  ::closedir(d);
  for (pid_t p : victims) ::kill(p, SIGKILL);
}

void delete_named_netns(const std::string& name) {
  const std::string path = kNetnsDir + name;
  ::umount2(path.c_str(), MNT_DETACH);
  ::unlink(path.c_str());
}

// ---- specs ----
void validate_link_name(const std::string& n) {
  const bool ok = !n.empty() && n.size() <= 10 && n != "lo" &&
                  std::all_of(n.begin(), n.end(), [](char c) {
                    return (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9');
                  });
  if (!ok) throw SetupError("link name '" + n + "': want 1..10 chars of [a-z0-9], not 'lo'");
}

struct Subnet {
  std::uint32_t network;  // host order
  int prefix;
};

Subnet parse_subnet(const std::string& s) {
  const auto slash = s.find('/');
  in_addr a{};
  if (slash == std::string::npos || ::inet_pton(AF_INET, s.substr(0, slash).c_str(), &a) != 1)
    throw SetupError("subnet '" + s + "': want a.b.c.d/len");
  char* end = nullptr;
  const long p = std::strtol(s.c_str() + slash + 1, &end, 10);
  if (*end != '\0' || p < 8 || p > 30) throw SetupError("subnet '" + s + "': prefix length must be 8..30");
  const std::uint32_t mask = ~0u << (32 - p);
  return {ntohl(a.s_addr) & mask, static_cast<int>(p)};
}

std::string ip_string(std::uint32_t host_order) {
  in_addr a{htonl(host_order)};
  char buf[INET_ADDRSTRLEN];
  ::inet_ntop(AF_INET, &a, buf, sizeof buf);
  return buf;
}

void validate_token(const std::string& what, const std::string& v) {
  const bool ok = !v.empty() && v.size() < 32 && std::all_of(v.begin(), v.end(), [](char c) {
    return std::isalnum(static_cast<unsigned char>(c)) || c == '.';
  });
  if (!ok) throw SetupError(what + " '" + v + "': unexpected characters");
}

// Probes a kernel feature in a throwaway (unnamed) namespace by running a tc command there.
std::optional<std::string> probe_in_scratch_ns(const std::vector<std::string>& argv) {
  std::optional<std::string> failure;
  std::thread t([&] {
    if (::unshare(CLONE_NEWNET) != 0) {
      failure = errno_text("unshare(CLONE_NEWNET)", errno);
      return;
    }
    const auto r = run_all({Cmd{argv, {}}});
    if (r[0].status != 0) failure = describe(Cmd{argv, {}}) + ": " + r[0].err;
  });
  t.join();
  return failure;
}

std::atomic<unsigned> g_serial{0};

}  // namespace

// tc rate ("1gbit", "400mbit", "10gbps", "125000bps", "1e9bit"...) in bytes per second.
double rate_bytes_per_second(const std::string& r) {
  std::size_t pos = 0;
  double v = 0;
  try {
    v = std::stod(r, &pos);
  } catch (const std::exception&) {
    throw SetupError("rate '" + r + "': not a tc rate (e.g. 1gbit, 400mbit, 10gbps)");
  }
  std::string unit = r.substr(pos);
  for (auto& c : unit) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  static const std::pair<const char*, double> units[] = {
      {"", 1.0 / 8},   {"bit", 1.0 / 8}, {"kbit", 1e3 / 8}, {"mbit", 1e6 / 8}, {"gbit", 1e9 / 8},
      {"tbit", 1e12 / 8}, {"bps", 1.0},  {"kbps", 1e3},     {"mbps", 1e6},     {"gbps", 1e9},
      {"tbps", 1e12}};
  for (const auto& [u, f] : units)
    if (unit == u && v > 0) return v * f;
  throw SetupError("rate '" + r + "': not a tc rate (e.g. 1gbit, 400mbit, 10gbps)");
}

// ---------------------------------------------------------------------------------------------
ScopedNetns::ScopedNetns(int netns_fd) {
  home_ = ::open("/proc/thread-self/ns/net", O_RDONLY | O_CLOEXEC);
  if (home_ < 0) throw SetupError(errno_text("open /proc/thread-self/ns/net", errno));
  if (::setns(netns_fd, CLONE_NEWNET) != 0) {
    const int e = errno;
    ::close(home_);
    home_ = -1;
    throw SetupError(errno_text("setns(CLONE_NEWNET)", e));
  }
}

ScopedNetns::~ScopedNetns() {
  if (home_ < 0) return;
  if (::setns(home_, CLONE_NEWNET) != 0) std::abort();  // cannot go on in the wrong namespace
  ::close(home_);
}

// ---------------------------------------------------------------------------------------------
struct Emulation::State {
  struct Host {
    std::string name;
    int fd = -1;     // the namespace
    int stats = -1;  // /proc/thread-self/net/dev opened inside it
    int ctl = -1;    // AF_INET socket inside it, for SIOCGIFFLAGS
  };
  std::vector<LinkSpec> links;
  std::vector<Subnet> subnets;
  std::vector<Host> hosts;
  Host sw;
  std::vector<std::string> registered;  // "/run/netns/<name>" paths we created (or tried to)

  ~State() {
    std::set<std::pair<dev_t, ino_t>> inodes;
    for (Host* h : all()) {
      struct stat st {};
      if (h->fd >= 0 && ::fstat(h->fd, &st) == 0) inodes.insert({st.st_dev, st.st_ino});
    }
    kill_processes_in(inodes);
    for (Host* h : all()) {
      for (int* fd : {&h->fd, &h->stats, &h->ctl})
        if (*fd >= 0) ::close(std::exchange(*fd, -1));
    }
    for (const auto& p : registered) {
      ::umount2(p.c_str(), MNT_DETACH);
      ::unlink(p.c_str());
      detail::unregister_netns(p.c_str());
    }
  }

  std::vector<Host*> all() {
    std::vector<Host*> v{&sw};
    for (auto& h : hosts) v.push_back(&h);
    return v;
  }

  std::size_t link_index(const std::string& link) const {
    for (std::size_t j = 0; j < links.size(); ++j)
      if (links[j].name == link) return j;
    throw std::out_of_range("lcmx::test::Emulation: no link named '" + link + "'");
  }
  const Host& host(int i) const {
    if (i < 0 || static_cast<std::size_t>(i) >= hosts.size())
      throw std::out_of_range("lcmx::test::Emulation: no host " + std::to_string(i));
    return hosts[static_cast<std::size_t>(i)];
  }

  // IFF_RUNNING of the host's interface (carrier as the stack sees it).
  bool running(int i, const std::string& ifname) const {
    ifreq ifr{};
    std::strncpy(ifr.ifr_name, ifname.c_str(), IFNAMSIZ - 1);
    if (::ioctl(host(i).ctl, SIOCGIFFLAGS, &ifr) != 0)
      throw SetupError(errno_text("SIOCGIFFLAGS " + ifname + " in " + host(i).name, errno));
    return (ifr.ifr_flags & IFF_RUNNING) != 0;
  }

  void wait_running(int i, const std::string& ifname, bool want) const {
    const auto deadline = Clock::now() + std::chrono::seconds(5);
    for (int guard = 0; guard < 1000000; ++guard) {
      if (running(i, ifname) == want) return;
      if (Clock::now() > deadline) break;
      std::this_thread::sleep_for(std::chrono::microseconds(200));  // polls a kernel state
    }
    throw SetupError("interface " + ifname + " in " + host(i).name + " did not go " +
                     (want ? "up" : "down") + " within 5 s");
  }

  std::pair<std::uint64_t, std::uint64_t> counters(int i, const std::string& link) const {
    const std::string ifname = links[link_index(link)].name;
    const int fd = host(i).stats;
    std::string text;
    char buf[8192];
    for (int guard = 0; guard < 1000; ++guard) {
      const ssize_t n = ::pread(fd, buf, sizeof buf, static_cast<off_t>(text.size()));
      if (n < 0 && errno == EINTR) continue;
      if (n <= 0) break;
      text.append(buf, static_cast<std::size_t>(n));
    }
    std::istringstream in(text);
    std::string line;
    while (std::getline(in, line)) {
      const auto colon = line.find(':');
      if (colon == std::string::npos) continue;
      std::string name = line.substr(0, colon);
      name.erase(0, name.find_first_not_of(' '));
      if (name != ifname) continue;
      std::istringstream f(line.substr(colon + 1));
      std::uint64_t v[9] = {};
      for (auto& x : v) f >> x;
      return {v[0], v[8]};  // rx_bytes, tx_bytes
    }
    throw SetupError("no counters for " + ifname + " in " + host(i).name);
  }
};

Emulation::Emulation(std::unique_ptr<State> s) : s_(std::move(s)) {}
Emulation::Emulation(Emulation&&) noexcept = default;
Emulation& Emulation::operator=(Emulation&&) noexcept = default;
Emulation::~Emulation() = default;

Emulation Emulation::create(const EmulationSpec& spec) {
  if (spec.hosts < 1 || spec.hosts > 250) throw SetupError("hosts must be 1..250");
  if (spec.links.empty() || spec.links.size() > 8) throw SetupError("links must be 1..8");
  std::string why;
  if (!netns_available(&why)) throw SetupError("network namespaces unavailable: " + why);

  remove_stale();
  auto s = std::make_unique<State>();
  const unsigned serial = g_serial.fetch_add(1);
  const pid_t pid = ::getpid();
  const std::string prefix = "lx" + std::to_string(pid) + "_" + std::to_string(serial) + "_";

  // Links: names, subnets, shaping parameters.
  bool any_delay = false;
  std::set<std::string> names;
  for (std::size_t j = 0; j < spec.links.size(); ++j) {
    LinkSpec l = spec.links[j];
    validate_link_name(l.name);
    if (!names.insert(l.name).second) throw SetupError("link name '" + l.name + "' used twice");
    if (l.subnet.empty()) {
      const unsigned v = ((static_cast<unsigned>(pid) % 512u) << 7) | ((serial % 16u) << 3) |
                         static_cast<unsigned>(j);
      l.subnet = "10." + std::to_string(v >> 8) + "." + std::to_string(v & 255u) + ".0/24";
    }
    const Subnet sn = parse_subnet(l.subnet);
    if (static_cast<std::uint64_t>(spec.hosts) + 2 > (std::uint64_t{1} << (32 - sn.prefix)))
      throw SetupError("subnet " + l.subnet + " too small for " + std::to_string(spec.hosts) + " hosts");
    if (l.rate) {
      validate_token("rate", *l.rate);
      rate_bytes_per_second(*l.rate);
    }
    if (l.delay) {
      validate_token("delay", *l.delay);
      any_delay = true;
    }
    s->links.push_back(l);
    s->subnets.push_back(sn);
  }
  if (any_delay && !delay_available(&why))
    throw SetupError("LinkSpec::delay needs the netem qdisc, which this kernel lacks: " + why);

  s->sw.name = prefix + "sw";
  for (int i = 0; i < spec.hosts; ++i) s->hosts.push_back({prefix + "h" + std::to_string(i)});

  if (!spec.tcp_congestion.empty()) allow_tcp_congestion(spec.tcp_congestion);

  // 1. Namespaces (registered first, so a watchdog can remove them even mid-creation).
  std::string batch;
  for (State::Host* h : s->all()) {
    s->registered.push_back(kNetnsDir + h->name);
    detail::register_netns(s->registered.back().c_str());
    batch += "netns add " + h->name + "\n";
  }
  run_checked({Cmd{{LCMX_TEST_IP, "-batch", "-"}, batch}});
  for (State::Host* h : s->all()) {
    h->fd = ::open((kNetnsDir + h->name).c_str(), O_RDONLY | O_CLOEXEC);
    if (h->fd < 0) throw SetupError(errno_text("open " + kNetnsDir + h->name, errno));
  }

  // 2. Inside each namespace, before any device exists (devices copy the defaults): IPv6 off
  //    (no router solicitations, MLD or DAD traffic on the links), counters, a control socket.
  std::exception_ptr err;
  on_thread_in(s->sw.fd, [&] {
    try {
      for (State::Host* h : s->all()) {
        if (::setns(h->fd, CLONE_NEWNET) != 0) throw SetupError(errno_text("setns " + h->name, errno));
        write_file("/proc/sys/net/ipv6/conf/all/disable_ipv6", "1");
        write_file("/proc/sys/net/ipv6/conf/default/disable_ipv6", "1");
        if (h == &s->sw) continue;
        if (!spec.tcp_congestion.empty()) set_tcp_congestion(spec.tcp_congestion, h->name);
        h->stats = ::open("/proc/thread-self/net/dev", O_RDONLY | O_CLOEXEC);
        if (h->stats < 0) throw SetupError(errno_text("open net/dev in " + h->name, errno));
        h->ctl = ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0);
        if (h->ctl < 0) throw SetupError(errno_text("socket in " + h->name, errno));
      }
    } catch (...) {
      err = std::current_exception();
    }
  });
  if (err) std::rethrow_exception(err);

  // 3. Switch: one bridge per link (no snooping, no STP: multicast floods), one veth per host
  //    and link, whose host end is created directly inside the host namespace.
  batch.clear();
  for (const auto& l : s->links) {
    const std::string br = "br_" + l.name;
    batch += "link add " + br + " type bridge mcast_snooping 0 stp_state 0 forward_delay 0\n";
    batch += "link set " + br + " up\n";
    for (std::size_t i = 0; i < s->hosts.size(); ++i) {
      const std::string port = "h" + std::to_string(i) + "_" + l.name;
      batch += "link add " + port + " type veth peer name " + l.name + " netns " + s->hosts[i].name + "\n";
      batch += "link set " + port + " master " + br + " up\n";
    }
  }
  run_checked({Cmd{{LCMX_TEST_IP, "-n", s->sw.name, "-batch", "-"}, batch}});

  // 4. Hosts (in parallel): lo, addresses, multicast route; qdiscs.
  std::vector<Cmd> cmds;
  for (std::size_t i = 0; i < s->hosts.size(); ++i) {
    std::string b = "link set lo up\nlink set lo multicast on\n";
    std::string tc;
    for (std::size_t j = 0; j < s->links.size(); ++j) {
      const auto& l = s->links[j];
      const auto& sn = s->subnets[j];
      b += "addr add " + ip_string(sn.network + static_cast<std::uint32_t>(i) + 1) + "/" +
           std::to_string(sn.prefix) + " dev " + l.name + "\n";
      b += "link set " + l.name + " up\n";
      // ARP retries every 100 ms instead of 1 s: a restored link carries unicast again within
      // ~0.1 s even if its neighbour entries failed while it was down.
      b += "ntable change name arp_cache dev " + l.name + " retrans 100\n";
      if (l.rate) {
        // burst: 1 ms at the rate, at least 32 KB (tbf needs >= one MTU; GSO skbs get split).
        const double bps = rate_bytes_per_second(*l.rate);
        const auto burst = static_cast<long long>(std::max(32768.0, std::min(bps / 1000, 16e6)));
        tc += "qdisc add dev " + l.name + " root handle 1: tbf rate " + *l.rate + " burst " +
              std::to_string(burst) + " latency 50ms\n";
        if (l.delay) tc += "qdisc add dev " + l.name + " parent 1:1 handle 10: netem delay " + *l.delay + "\n";
      } else if (l.delay) {
        tc += "qdisc add dev " + l.name + " root handle 10: netem delay " + *l.delay + "\n";
      }
    }
    switch (spec.routes) {
      case MulticastRoute::first_link:
        b += "route add 224.0.0.0/4 dev " + s->links[0].name + "\n";
        break;
      case MulticastRoute::default_route: {
        const auto& sn = s->subnets[0];
        const std::uint32_t gateway = sn.network + static_cast<std::uint32_t>((std::uint64_t{1} << (32 - sn.prefix)) - 2);
        if (gateway <= sn.network + static_cast<std::uint32_t>(spec.hosts))
          throw SetupError("MulticastRoute::default_route: subnet " + s->links[0].subnet + " has no address left for a gateway");
        b += "route add default via " + ip_string(gateway) + " dev " + s->links[0].name + "\n";
        break;
      }
      case MulticastRoute::none:
        break;
    }
    cmds.push_back(Cmd{{LCMX_TEST_IP, "-n", s->hosts[i].name, "-batch", "-"}, b});
    if (!tc.empty()) cmds.push_back(Cmd{{LCMX_TEST_TC, "-n", s->hosts[i].name, "-batch", "-"}, tc});
  }
  run_checked(cmds);

  // 5. Ready when every host interface has carrier.
  for (std::size_t i = 0; i < s->hosts.size(); ++i)
    for (const auto& l : s->links) s->wait_running(static_cast<int>(i), l.name, true);
  return Emulation(std::move(s));
}

int Emulation::hosts() const { return static_cast<int>(s_->hosts.size()); }
const std::vector<LinkSpec>& Emulation::links() const { return s_->links; }
const std::string& Emulation::ns(int host) const { return s_->host(host).name; }
const std::string& Emulation::switch_ns() const { return s_->sw.name; }
int Emulation::ns_fd(int host) const { return s_->host(host).fd; }

std::string Emulation::address(int host, const std::string& link) const {
  s_->host(host);
  return ip_string(s_->subnets[s_->link_index(link)].network + static_cast<std::uint32_t>(host) + 1);
}

std::string Emulation::interface(int host, const std::string& link) const {
  s_->host(host);
  return s_->links[s_->link_index(link)].name;
}

void Emulation::set_link_up(int host, const std::string& link, bool up) {
  s_->host(host);
  const auto& l = s_->links[s_->link_index(link)];
  const std::string port = "h" + std::to_string(host) + "_" + l.name;
  run_checked({Cmd{{LCMX_TEST_IP, "-n", s_->sw.name, "link", "set", port, up ? "up" : "down"}, {}}});
  s_->wait_running(host, l.name, up);
}

std::uint64_t Emulation::tx_bytes(int host, const std::string& link) const {
  return s_->counters(host, link).second;
}
std::uint64_t Emulation::rx_bytes(int host, const std::string& link) const {
  return s_->counters(host, link).first;
}

Child Emulation::spawn(int host, std::vector<std::string> argv, Env env) const {
  const auto& h = s_->host(host);
  return spawn_child(argv, env, h.fd, h.name);
}

void Emulation::run_on_thread(int host, const std::function<void()>& body) const {
  on_thread_in(s_->host(host).fd, body);
}

int Emulation::remove_stale() {
  DIR* d = ::opendir(kNetnsDir.c_str());
  if (d == nullptr) return 0;
  std::vector<std::string> stale;
  for (int guard = 0; guard < 100000; ++guard) {
    const dirent* e = ::readdir(d);
    if (e == nullptr) break;
    const std::string n = e->d_name;
    const auto parsed = parse_name(n);
    if (!parsed) continue;
    if (::kill(parsed->pid, 0) == 0 || errno != ESRCH) continue;  // creator alive (or unknown)
    stale.push_back(n);
  }
  ::closedir(d);
  std::set<std::pair<dev_t, ino_t>> inodes;
  for (const auto& n : stale) {
    struct stat st {};
    if (::stat((kNetnsDir + n).c_str(), &st) == 0) inodes.insert({st.st_dev, st.st_ino});
  }
  kill_processes_in(inodes);
  for (const auto& n : stale) delete_named_netns(n);
  return static_cast<int>(stale.size());
}

bool netns_available(std::string* why) {
  static const std::string reason = [] {
    if (::access(LCMX_TEST_IP, X_OK) != 0) return std::string(LCMX_TEST_IP " not executable");
    std::ifstream st("/proc/self/status");
    std::string line;
    bool cap = false;
    while (std::getline(st, line)) {
      if (line.rfind("CapEff:", 0) == 0) {
        const unsigned long long caps = std::strtoull(line.c_str() + 7, nullptr, 16);
        cap = (caps >> 21) & 1u;  // CAP_SYS_ADMIN
      }
    }
    if (!cap) return std::string("no CAP_SYS_ADMIN (run the tests as root)");
    std::string r;
    std::thread t([&] {
      if (::unshare(CLONE_NEWNET) != 0) r = errno_text("unshare(CLONE_NEWNET)", errno);
    });
    t.join();
    if (!r.empty()) return r;
    if (::mkdir("/run/netns", 0755) != 0 && errno != EEXIST) return errno_text("mkdir /run/netns", errno);
    return std::string();
  }();
  if (why != nullptr) *why = reason;
  return reason.empty();
}

bool delay_available(std::string* why) {
  static const std::string reason = [] {
    if (!netns_available()) return std::string("network namespaces unavailable");
    const auto f = probe_in_scratch_ns({LCMX_TEST_TC, "qdisc", "add", "dev", "lo", "root", "netem", "delay", "1ms"});
    return f ? *f : std::string();
  }();
  if (why != nullptr) *why = reason;
  return reason.empty();
}

}  // namespace lcmx::test
