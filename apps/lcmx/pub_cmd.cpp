// `lcmx pub CHANNEL TYPE [JSON]`: publishes messages written as JSON, encoded with the `.lcm`
// files of the type path (types::from_json + types::encode), through lcmx: a raw publisher
// that announces TYPE's name and fingerprint, so typed subscribers of that type match it on
// every path (in this host's shm, other hosts over UDP or the bridges; --udp also stock LCM).
//
// Timing: message k is due at start + k / rate on CLOCK_MONOTONIC (absolute deadlines: no
// drift); a message more than one period late is published at once and the deadlines it
// missed are skipped (counted), never sent in a burst.
// Threads: the main thread does everything; signals arrive through StopSignals (tap.hpp).
#include <spdlog/spdlog.h>
#include <sys/prctl.h>
#include <unistd.h>

#include <cmath>
#include <cstring>
#include <iostream>

#include "echo_cmds.hpp"
#include "log_common.hpp"
#include "tap.hpp"

namespace lcmx::cli {
namespace {

struct PubOptions {
  std::string channel;
  std::string type;
  std::optional<std::string> json;
  std::vector<std::string> types;
  double rate = 0;  // 0: not given
  long long count = 0;
  bool once = false;
  int wait_subscribers = 1;
  double wait_timeout_s = 5;
  bool no_wait = false;
  bool udp = false;
  bool quiet = false;
  bool json_summary = false;  // --json: a summary line on stdout at the end
  const Globals* g = nullptr;
};
PubOptions g_pub;

using Clock = std::chrono::steady_clock;

// Reads stdin one line at a time while watching for a stop (no blocking read a signal could
// not interrupt).
class LineReader {
 public:
  explicit LineReader(StopSignals& stop) : stop_(stop) {}
  // The next line (without '\n'); nullopt at EOF or on a stop.
  std::optional<std::string> next() {
    for (;;) {
      if (const auto nl = buf_.find('\n'); nl != std::string::npos) {
        std::string line = buf_.substr(0, nl);
        buf_.erase(0, nl + 1);
        ++line_no_;
        return line;
      }
      if (eof_) {
        if (buf_.empty()) return std::nullopt;
        ++line_no_;
        return std::exchange(buf_, {});
      }
      bool ready = false;
      if (stop_.wait(std::chrono::nanoseconds(-1), STDIN_FILENO, &ready)) return std::nullopt;
      if (!ready) continue;
      char chunk[65536];
      const ssize_t n = ::read(STDIN_FILENO, chunk, sizeof chunk);
      if (n < 0 && errno == EINTR) continue;
      if (n <= 0) eof_ = true;
      else buf_.append(chunk, static_cast<std::size_t>(n));
    }
  }
  long line_no() const { return line_no_; }

 private:
  StopSignals& stop_;
  std::string buf_;
  bool eof_ = false;
  long line_no_ = 0;
};

// The type by package-qualified name; an error naming what is there otherwise.
const types::StructType* find_type(const types::TypeRegistry& reg, const std::string& name, std::string& error) {
  if (const auto* t = reg.find(name)) return t;
  if (reg.size() == 0) {
    error = "unknown type '" + name + "': no type path (give --types DIR|FILE or set LCMX_TYPES_PATH)";
    return nullptr;
  }
  std::string similar;
  for (const auto& t : reg.types())
    if (t->name == name || t->name == name.substr(name.rfind('.') + 1)) similar += (similar.empty() ? "" : ", ") + t->full_name();
  error = "unknown type '" + name + "' (not in the type path, " + std::to_string(reg.size()) + " types";
  error += similar.empty() ? "; types are named package.type, e.g. " + reg.types().front()->full_name() + ")"
                           : "; did you mean " + similar + "?)";
  return nullptr;
}

int run_pub() {
  const auto& o = g_pub;
  spdlog::set_level(spdlog::level::warn);
  if (o.channel.size() > kMaxChannelLength) {
    std::cerr << "lcmx pub: channel '" << o.channel << "' is longer than " << kMaxChannelLength << " bytes\n";
    return 2;
  }
  types::TypeRegistry reg;
  try {
    reg = load_types(o.types);
  } catch (const types::Error& e) {
    std::cerr << "lcmx pub: " << e.what() << "\n";
    return 1;
  }
  std::string error;
  const types::StructType* type = find_type(reg, o.type, error);
  if (!type) {
    std::cerr << "lcmx pub: " << error << "\n";
    return 1;
  }
  const bool from_stdin = !o.json || *o.json == "-";
  std::vector<std::uint8_t> fixed;  // the message of the JSON argument
  if (!from_stdin) {
    try {
      fixed = types::encode(*type, types::from_json(*type, *o.json));
    } catch (const types::Error& e) {
      std::cerr << "lcmx pub: " << e.what() << "\n";
      return 1;
    }
  }
  // How many: --once 1, -n COUNT, else (JSON argument) until stopped / (stdin) until EOF.
  const long long count = o.once ? 1 : o.count;
  // The JSON argument repeats at 1 Hz unless told otherwise (like `ros2 topic pub`); stdin
  // lines go out as they come unless --rate is given.
  const double rate = o.rate > 0 ? o.rate : (from_stdin ? 0.0 : 1.0);

  StopSignals stop;
  ::prctl(PR_SET_TIMERSLACK, 1UL, 0, 0, 0);
  std::optional<Runtime> rt;
  std::optional<Node> node;
  RawPublisher pub;
  try {
    rt.emplace(Runtime::create(runtime_options(*o.g, o.udp)));
    node.emplace(rt->create_node("lcmx_pub"));
    PublisherOptions po;
    po.max_message_size = std::max(po.max_message_size, fixed.size());
    po.shm_initial_slot_size = std::max(po.shm_initial_slot_size, fixed.size());
    pub = node->advertise_raw(o.channel, type->full_name(), static_cast<std::int64_t>(type->fingerprint), po);
  } catch (const std::exception& e) {
    std::cerr << "lcmx pub: " << e.what() << "\n";
    return 1;
  }
  if (!o.quiet)
    std::cerr << "lcmx pub: " << type->full_name() << " on " << o.channel
              << (from_stdin ? " from stdin (one JSON object per line)" : "") << std::endl;

  // Subscribers first: what is published before a subscriber matched is not received.
  if (!o.no_wait && o.wait_subscribers > 0) {
    const auto deadline = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                             std::chrono::duration<double>(o.wait_timeout_s));
    const auto n = static_cast<std::size_t>(o.wait_subscribers);
    while (!pub.wait_for_subscribers(n, std::chrono::milliseconds(20))) {
      if (stop.wait(std::chrono::nanoseconds(0))) return 0;
      if (Clock::now() >= deadline) {
        std::cerr << "lcmx pub: " << pub.subscriber_count() << " of " << n << " subscribers after "
                  << o.wait_timeout_s << " s; publishing anyway (stock LCM subscribers are not seen: "
                  << "--udp reaches them; --no-wait skips waiting)\n";
        break;
      }
    }
  }

  LineReader lines(stop);
  const auto period = rate > 0 ? std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(1.0 / rate))
                               : Clock::duration::zero();
  Clock::time_point due{};
  bool have_due = false;
  long long published = 0, skipped = 0;
  int rc = 0;
  std::vector<std::uint8_t> msg;
  while (count == 0 || published < count) {
    const std::vector<std::uint8_t>* bytes = &fixed;
    if (from_stdin) {
      auto line = lines.next();
      if (!line) break;
      if (line->find_first_not_of(" \t\r") == std::string::npos) continue;
      try {
        msg = types::encode(*type, types::from_json(*type, *line));
      } catch (const types::Error& e) {
        std::cerr << "lcmx pub: stdin line " << lines.line_no() << ": " << e.what() << "\n";
        rc = 1;
        break;
      }
      bytes = &msg;
    }
    if (rate > 0) {
      if (!have_due) {
        due = Clock::now();
        have_due = true;
      }
      if (stop.wait_until(due)) break;
      const auto now = Clock::now();
      if (now - due > period) {  // more than a period late: skip the missed deadlines
        const auto missed = (now - due) / period;
        skipped += missed;
        due += missed * period;
      }
      due += period;
    } else if (stop.wait(std::chrono::nanoseconds(0))) {
      break;
    }
    try {
      pub.publish(std::as_bytes(std::span(*bytes)));
    } catch (const std::exception& e) {
      std::cerr << "lcmx pub: " << e.what() << "\n";
      rc = 1;
      break;
    }
    ++published;
  }
  if (!o.quiet) {
    std::cerr << "lcmx pub: published " << published << (published == 1 ? " message" : " messages");
    if (skipped > 0) std::cerr << " (" << skipped << " deadlines skipped: publishing was late)";
    std::cerr << "\n";
  }
  if (o.json_summary) {
    char fp[17];
    std::snprintf(fp, sizeof fp, "%016llx", static_cast<unsigned long long>(type->fingerprint));
    std::cout << "{\"channel\":" << json_str(o.channel) << ",\"type\":" << json_str(type->full_name())
              << ",\"fingerprint\":\"" << fp << "\",\"published\":" << published
              << ",\"deadlines_skipped\":" << skipped << ",\"subscribers\":" << pub.subscriber_count()
              << ",\"ok\":" << (rc == 0 ? "true" : "false") << "}" << std::endl;
  }
  return rc;
}

}  // namespace

Verb add_pub(CLI::App& app, const Globals& g) {
  g_pub.g = &g;
  auto* c = app.add_subcommand(
      "pub",
      "publish messages written as JSON, typed with the .lcm files of the type path (JSON, or one JSON object "
      "per line on stdin)");
  c->add_option("channel", g_pub.channel, "channel")->required();
  c->add_option("type", g_pub.type, "the message type, package-qualified (lcmx_examples.pose_t)")->required();
  c->add_option("json", g_pub.json,
                "the message as JSON, e.g. '{\"position\": [1, 2, 3]}'; fields not given are zero, variable arrays "
                "set their size fields; '-' or none: one message per line of stdin");
  c->add_option("-t,--types", g_pub.types,
                ".lcm file or directory (searched recursively; repeatable, or a ':' list); default LCMX_TYPES_PATH")
      ->allow_extra_args(false);
  c->add_option("-r,--rate", g_pub.rate,
                "messages per second, on absolute deadlines (default: 1 for a JSON argument; stdin lines as they come)")
      ->check(CLI::Range(0.001, 1e6));
  c->add_option("-n,--count", g_pub.count, "publish this many messages, then exit (0: until stopped or EOF)")
      ->check(non_negative_number());
  c->add_flag("-1,--once", g_pub.once, "publish one message, then exit");
  c->add_option("--wait-subscribers", g_pub.wait_subscribers,
                "before the first message, wait until this many lcmx subscribers are matched")
      ->check(CLI::Range(0, 100000))
      ->capture_default_str();
  c->add_option("--wait-timeout", g_pub.wait_timeout_s,
                "seconds to wait for them; then publish anyway (with a warning)")
      ->check(positive_number())
      ->capture_default_str();
  c->add_flag("--no-wait", g_pub.no_wait, "publish at once, without waiting for subscribers");
  c->add_flag("--udp", g_pub.udp,
              "also send on the UDP groups, for stock LCM subscribers (host-local group; the vehicle group too "
              "when configured); on the host-local group small messages only (<= LCMX_UDP_LIMIT)");
  c->add_flag("-q,--quiet", g_pub.quiet, "no messages on stderr but errors");
  c->add_flag("--json", g_pub.json_summary,
              "at the end, one JSON line on stdout: {channel, type, fingerprint (hex), published, "
              "deadlines_skipped, subscribers, ok}");
  c->footer(
      "JSON rules (lcmx::types::from_json): a field that does not exist is an error naming it; integers must "
      "fit their type; a fixed array needs exactly its length; null/\"nan\"/\"inf\" for non-finite floats. "
      "Exit: 0 when done or on SIGINT/SIGTERM, 1 for a bad type path, type, JSON or stdin line, 2 for bad "
      "arguments.");
  return {c, [] { return run_pub(); }};
}

}  // namespace lcmx::cli
