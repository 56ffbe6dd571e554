// The ping-pong latency protocol of lcmx_bench_latency and lcmx_bench_udp (also spoken by
// bench/python/bench_python.py): one method = a subscriber child and a publisher child; the
// publisher sends the next message only after the subscriber acked the previous one (or after
// the timeout: lost), so there is no queueing and every loop is bounded. The ack travels on a
// pipe, never on the transport under test, and is not part of the measured one-way time.
//
// Children's fds (set up by run_pair before exec):
//   3 kReportFd  child -> orchestrator: "ready" | "error <text>" | "note <text>" |
//                "sent <size> <count> <ack_timeouts>" | "lat <size> <count> <ns>..." | "done"
//   4 kAckFd     subscriber -> publisher: 8-byte seq records (kMatchedRecord once matched)
//   5 kCtlFd     publisher -> subscriber: 'E' when the run is over
#pragma once

#include <sys/types.h>

#include <climits>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "process.hpp"
#include "stats.hpp"

namespace lcmxbench {

// ---- the plan ----

// One message size of the run: `warmup` unmeasured messages, then `messages` measured ones.
struct SizePlan {
  std::size_t size = 0;
  int warmup = 0;
  int messages = 0;
};
// Counts per size class when no --messages/--warmup is given: up to 100 KB, up to 2 MB, above.
struct PlanDefaults {
  int warmup[3];
  int messages[3];
};
// The plan of `sizes` (parse_size, >= 16 B) with `defaults`, overridden by messages > 0 and
// warmup >= 0. Throws std::invalid_argument naming a bad size.
std::vector<SizePlan> make_plan(const std::vector<std::string>& sizes, const PlanDefaults& defaults,
                                int messages, int warmup);
std::string plan_to_string(const std::vector<SizePlan>& plan);    // "1024:20:200,..."
std::vector<SizePlan> plan_from_string(const std::string& text);  // throws std::invalid_argument
std::size_t max_size(const std::vector<SizePlan>& plan);          // largest size in the plan
// "1 KB 20+200, 6 MB 5+50" (size, warmup + measured).
std::string plan_text(const std::vector<SizePlan>& plan);

// Sequence numbers are unique over the whole run of one method: seq = (k << 1) | measured.
inline std::int64_t make_seq(std::int64_t k, bool measured) { return (k << 1) | (measured ? 1 : 0); }
inline bool seq_measured(std::int64_t seq) { return (seq & 1) != 0; }

// ---- the children's side ----

inline constexpr int kAckFd = 4;
inline constexpr int kCtlFd = 5;
inline constexpr std::int64_t kMatchedRecord = INT64_MIN;  // on kAckFd: the subscriber is matched

// Everything a role needs, from the (hidden) command-line options of a child.
struct RoleConfig {
  std::string role;            // e.g. "floor-sub", "lcmx-shm-pub", "lcmx-intra"
  std::vector<SizePlan> plan;
  std::string name;            // unique per run: shm segment / channel names
  std::string url;             // liblcm udpm URL or lcmx discovery URL
  std::string wait = "block";  // lcmx subscriber wait strategy (wait_strategy())
  int timeout_ms = 200;        // receive timeout per message (then it counts as lost)
  int pub_cpu = -1;            // lcmx-intra only: CPU of the publishing thread (-1: none)
  int sub_cpu = -1;            // CPU of the subscriber's callback thread (-1: none)
};

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

// Writes an ack record (8-byte seq) on `fd`. Async-signal-safe, thread-safe.
void send_ack(int fd, std::int64_t seq) noexcept;
// Waits until the ack `seq` arrives on `fd` (older acks are skipped). Returns false on timeout
// or EOF.
bool wait_ack(int fd, std::int64_t seq, int timeout_ms);
// Waits for 'E' (or EOF) on `fd`, up to timeout_ms. Returns true if it came.
bool wait_end(int fd, int timeout_ms);
// The publisher's last word to the subscriber: 'E' on kCtlFd.
void send_end();

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

// ---- the orchestrator's side ----

struct SizeResult {
  std::optional<int> sent;  // from the publisher's "sent" line
  int ack_timeouts = 0;
  std::optional<std::vector<std::int64_t>> lat;  // from the subscriber's "lat" line
};

// One method's run (or its rounds pooled with merge()).
struct MethodResult {
  std::string method;
  std::vector<std::string> errors, notes;
  std::map<std::size_t, SizeResult> sizes;
  bool failed() const { return !errors.empty(); }
};

// Folds one report line of a child into `r` ("ready" and "done" are ignored).
void parse_line(MethodResult& r, const std::string& line);
// Pools another round of the same method into `into`: samples and sent counts add up, errors
// are kept, notes once each.
void merge(MethodResult& into, MethodResult&& more);

// A size measured completely: the publisher said how many it sent, the subscriber reported.
struct Cell {
  bool ok = false;
  Stats st;  // µs
  int sent = 0;
  int lost = 0;
};
Cell cell_of(const MethodResult& m, std::size_t size);
// "p50 / p99" µs, "(lost n/N)" after it when `lost` says so or any was lost; "failed" or "—".
std::string cell_text(const MethodResult& m, std::size_t size, bool always_lost = false);

// One method: a subscriber child (sub_argv) and, once it says "ready", a publisher child
// (pub_argv), wired with the pipes above; or a single child (pub_argv empty) that does both,
// with only its report pipe. Runs until both closed their report pipes, the deadline (then both
// are killed: "timed out") or a stop signal; collects their lines and exit statuses.
struct Pair {
  std::string method;
  std::vector<std::string> sub_argv, pub_argv;
  int sub_cpu = -1, pub_cpu = -1;      // -1: not pinned
  int sub_netns = -1, pub_netns = -1;  // -1: ours
  int deadline_ms = 60'000;
};
struct PairOutcome {
  MethodResult result;
  bool killed = false;  // a child was killed (timed out or died of a signal)
};
PairOutcome run_pair(const Pair& pair);
// The per-size figures of a method, its failures and notes on stderr ("[tag] ...").
void progress_of(const std::string& tag, const MethodResult& r, const std::vector<SizePlan>& plan);

}  // namespace lcmxbench
