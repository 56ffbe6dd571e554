// Shared pieces of lcmx_bench_latency: clock, the per-size plan, the child-process protocol,
// the ping-pong driver used by every publisher role and the latency recorder used by every
// subscriber role.
//
// Process model: the parent ("orchestrator") never publishes or subscribes itself. For each
// method it starts a subscriber child, waits for its "ready" line, starts a publisher child
// and reads both children's report lines. Children talk to each other only through the
// method under test plus a side channel for acks that is not part of the measured time.
#pragma once

#include <sys/types.h>

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

namespace lcmxbench {

// ---- child processes (shared by lcmx_bench_latency, _udp and _bridge) ----

// This binary's path (/proc/self/exe), to start its roles.
std::string self_exe();

// A close-on-exec pipe; both ends closed on destruction.
struct Pipe {
  int r = -1, w = -1;
  Pipe();  // throws std::runtime_error
  Pipe(const Pipe&) = delete;
  Pipe& operator=(const Pipe&) = delete;
  ~Pipe() { close_r(), close_w(); }
  void close_r();
  void close_w();
};

// Starts argv (argv[0] searched in PATH when it has no '/') with fds[i] as fd 3 + i (-1: left
// closed; at most 8), pinned to `cpu` (-1: not pinned), inside network namespace `netns_fd`
// (-1: ours). The child gets SIGKILL if this process dies. Throws std::runtime_error if fork
// fails; exec failures show as exit code 127 (125: setns/dup failed, 126: pinning failed).
pid_t spawn_child(const std::vector<std::string>& argv, const std::vector<int>& fds, int cpu,
                  int netns_fd = -1);

// `argv` run under `taskset -c cpu` (for starters that take an argv, e.g. Emulation::spawn);
// unchanged when cpu < 0.
std::vector<std::string> taskset(int cpu, std::vector<std::string> argv);

// Lines a child writes to a pipe (its report fd), read without blocking: call pump() when
// poll() says `fd` is readable. Complete lines go to `lines`; `eof` once the child closed it.
struct LineReader {
  int fd = -1;
  std::string buf;
  bool eof = false;
  std::vector<std::string> lines;
  void pump();
  bool has(const std::string& prefix) const;  // a line starting with prefix arrived
};

// Polls the readers until every one is at EOF or until() holds (true), or the deadline passes
// or `stop` is set (false).
bool pump_until(const std::vector<LineReader*>& readers, std::int64_t deadline,
                const std::function<bool()>& until, const std::atomic<int>& stop);

// Waits for child `pid` to exit; SIGKILLs it once `timeout_ms` passed or `stop` is set.
// Returns its wait status; *killed (if given) tells whether it had to be killed.
int reap_child(pid_t pid, int timeout_ms, const std::atomic<int>& stop, bool* killed = nullptr);

// CLOCK_MONOTONIC in ns. Processes on one host share it, so latency = receive - send.
std::int64_t now_ns();

// One message size of the run: `warmup` unmeasured messages, then `messages` measured ones.
struct SizePlan {
  std::size_t size = 0;
  int warmup = 0;
  int messages = 0;
};
std::string plan_to_string(const std::vector<SizePlan>& plan);    // "1024:20:200,..."
std::size_t max_size(const std::vector<SizePlan>& plan);          // largest size in the plan
std::vector<SizePlan> plan_from_string(const std::string& text);  // throws std::invalid_argument
// "100K", "6M", "1500" (K = 1024, M = 1024*1024, optional B) -> bytes in [min_bytes, 64 MB].
// Throws std::invalid_argument naming the text.
std::size_t parse_size(const std::string& text, std::size_t min_bytes);
std::string size_label(std::size_t bytes);                        // "1 KB", "6 MB"
std::string fmt_us(double us);                                    // "4.3", "857" (table cells)

// Sequence numbers are unique over the whole run of one method: seq = (k << 1) | measured.
inline std::int64_t make_seq(std::int64_t k, bool measured) { return (k << 1) | (measured ? 1 : 0); }
inline bool seq_measured(std::int64_t seq) { return (seq & 1) != 0; }

// File descriptors a child inherits (fixed numbers, set up by the parent before exec).
inline constexpr int kReportFd = 3;  // child -> parent: text lines (see Report)
inline constexpr int kAckFd = 4;     // subscriber -> publisher: 8-byte seq records
inline constexpr int kCtlFd = 5;     // publisher -> subscriber: 'E' when the run is over
inline constexpr std::int64_t kMatchedRecord = INT64_MIN;  // on kAckFd: subscriber is matched

// Everything a role needs, from the (hidden) command-line options of a child.
struct RoleConfig {
  std::string role;           // e.g. "floor-sub", "lcmx-shm-pub", "lcmx-intra"
  std::vector<SizePlan> plan;
  std::string name;           // unique per run: shm segment / channel names
  std::string url;            // liblcm udpm URL or lcmx discovery URL
  std::string wait = "block";  // lcmx subscriber wait strategy: block (lcmx default) | spin | adaptive | busy
  int timeout_ms = 200;       // receive timeout per message (then it counts as lost)
  int pub_cpu = -1;           // lcmx-intra only: CPU of the publishing thread (-1: none)
  int sub_cpu = -1;           // CPU of the subscriber's callback thread (-1: none)
};

// Report lines written by children on kReportFd, one write() per line:
//   ready | error <text> | note <text> | sent <size> <count> <ack_timeouts>
//   lat <size> <count> <ns>... | done
void report_line(const std::string& line);
void report_error(const std::string& text);

// Pins the calling thread to `cpu` (no-op for cpu < 0). Returns false on failure.
bool pin_thread(int cpu);

// Subscriber side: latencies per size, preallocated, filled by one thread at a time.
class Recorder {
 public:
  explicit Recorder(const std::vector<SizePlan>& plan);
  // Records one received message. Unknown sizes and warmup messages are ignored.
  void record(std::size_t size, std::int64_t seq, std::int64_t latency_ns) noexcept;
  // Writes one "lat" line per planned size.
  void report() const;

 private:
  std::vector<SizePlan> plan_;
  std::vector<std::vector<std::int64_t>> lat_;
};

// Writes an ack record (8-byte seq) on kAckFd. Async-signal-safe, thread-safe.
void send_ack(int fd, std::int64_t seq) noexcept;
// Waits until the ack `seq` arrives on `fd` (older acks are skipped). Returns false on timeout
// or EOF.
bool wait_ack(int fd, std::int64_t seq, int timeout_ms);
// Waits for 'E' (or EOF) on kCtlFd, up to timeout_ms. Returns true if it came.
bool wait_end(int fd, int timeout_ms);

// The ping-pong driver of every publisher role: for each size, prepare(size), then for
// warmup + measured messages send(seq, size) and wait_ack(seq). A message with no ack within
// timeout_ms is lost. Reports "sent" lines. Returns false (after reporting an error) if no
// warmup message of the first size was acknowledged: the method does not work at all.
struct Driver {
  std::function<void(std::size_t size)> prepare;
  std::function<void(std::int64_t seq, std::size_t size)> send;
  std::function<bool(std::int64_t seq, int timeout_ms)> wait_ack;
};
bool run_driver(const RoleConfig& cfg, const Driver& d);

// Roles (each returns the child's exit code).
int run_floor_sub(const RoleConfig& cfg);
int run_floor_pub(const RoleConfig& cfg);
int run_liblcm_sub(const RoleConfig& cfg);
int run_liblcm_pub(const RoleConfig& cfg);
int run_lcmx_sub(const RoleConfig& cfg, bool loan);
int run_lcmx_pub(const RoleConfig& cfg, bool loan);
int run_lcmx_intra(const RoleConfig& cfg);

}  // namespace lcmxbench
