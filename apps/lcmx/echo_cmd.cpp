// `lcmx echo CHANNEL...`: prints the messages of the matching channels, decoded with the `.lcm`
// files of the type path (--types / LCMX_TYPES_PATH): the type is the one whose fingerprint
// is the message's first 8 bytes, as lcm-spy finds it in jars. Every path (shm, bridges, UDP
// from other hosts, stock LCM programs) through the channel tap (tap.hpp).
//
// Threads: the node's executor decodes and writes each message to stdout in its callback (a
// slow terminal makes lcmx drop the oldest messages, counted; publishers are never slowed);
// the main thread waits for a signal or for -n to be reached, then prints drops to stderr.
#include <spdlog/spdlog.h>

#include <atomic>
#include <cstdio>
#include <iostream>
#include <mutex>

#include "echo_cmds.hpp"
#include "log_common.hpp"
#include "tap.hpp"

namespace lcmx::cli {
namespace {

struct EchoOptions {
  std::vector<std::string> channels;
  bool regex = false;
  std::vector<std::string> types;
  bool json = false;
  bool raw = false;
  std::string field;
  long long count = 0;
  std::size_t max_array = 10;
  bool no_header = false;
  std::size_t queue_depth = 100;
  const Globals* g = nullptr;
};
EchoOptions g_echo;

// "0a 1b ..." 16 bytes a line with offsets (text), or one hex string (JSON).
std::string hex_dump(std::span<const std::byte> d) {
  static const char* hex = "0123456789abcdef";
  std::string out;
  for (std::size_t i = 0; i < d.size(); i += 16) {
    char off[32];
    std::snprintf(off, sizeof off, "  %06zx ", i);
    out += off;
    for (std::size_t k = i; k < std::min(d.size(), i + 16); ++k) {
      const auto b = static_cast<unsigned>(d[k]);
      out += ' ';
      out += hex[b >> 4];
      out += hex[b & 0xf];
    }
    out += '\n';
  }
  return out;
}
std::string hex_string(std::span<const std::byte> d) {
  static const char* hex = "0123456789abcdef";
  std::string out;
  out.reserve(d.size() * 2);
  for (std::byte x : d) {
    const auto b = static_cast<unsigned>(x);
    out += hex[b >> 4];
    out += hex[b & 0xf];
  }
  return out;
}

class Printer {
 public:
  Printer(const EchoOptions& o, const types::TypeRegistry& reg, StopSignals& stop) : o_(o), reg_(reg), stop_(stop) {}

  // Executor thread.
  void on_message(const RawMessage& m) {
    if (done_.load(std::memory_order_relaxed)) return;
    const std::int64_t now = wall_us();
    std::string out = o_.json ? json(m, now) : text(m, now);
    std::lock_guard lock(mu_);
    if (done_.load()) return;
    if (std::fwrite(out.data(), 1, out.size(), stdout) != out.size() || std::fflush(stdout) != 0) {
      write_failed_ = true;  // stdout closed (| head): stop quietly
      done_.store(true);
      stop_.request_stop();
      return;
    }
    ++printed_;
    if (o_.count > 0 && printed_ >= static_cast<std::uint64_t>(o_.count)) {
      done_.store(true);
      stop_.request_stop();
    }
  }
  std::uint64_t printed() {
    std::lock_guard lock(mu_);
    return printed_;
  }
  bool write_failed() {
    std::lock_guard lock(mu_);
    return write_failed_;
  }

 private:
  // What the message is: its type, or why it cannot be decoded.
  struct Decoded {
    const types::StructType* type = nullptr;
    std::optional<std::uint64_t> fingerprint;
    std::optional<types::Value> value;  // the message, or the --field part of it
    std::string error;
  };
  Decoded decode(const RawMessage& m) const {
    Decoded d;
    d.fingerprint = types::message_fingerprint(m.data.data(), m.data.size());
    if (!d.fingerprint) {
      d.error = "too short for an LCM message (no 8-byte fingerprint)";
      return d;
    }
    d.type = reg_.find(*d.fingerprint);
    if (o_.raw) return d;
    if (!d.type) {
      d.error = reg_.size() == 0 ? "unknown type: no type path (give --types DIR or set LCMX_TYPES_PATH)"
                                 : "unknown type: no type in the type path has this fingerprint";
      return d;
    }
    try {
      types::Value v = types::decode(*d.type, m.data.data(), m.data.size());
      d.value = o_.field.empty() ? std::move(v) : types::field(v, o_.field);
    } catch (const types::Error& e) {
      d.error = e.what();
    }
    return d;
  }

  std::string text(const RawMessage& m, std::int64_t now) const {
    const Decoded d = decode(m);
    std::string out;
    if (!o_.no_header || !d.error.empty()) {
      // The channel name is whatever the sender chose: escaped (safe_text.hpp), as every name
      // from the network or a file the tools print.
      out = "--- " + printable(m.channel) + "  " + format_us(now) + "  " + std::to_string(m.data.size()) + " bytes";
      if (d.type) out += "  " + printable(d.type->full_name());
      else if (d.fingerprint) out += "  fingerprint " + hex_fingerprint(*d.fingerprint);
      if (!d.error.empty()) out += "  (" + printable(d.error) + ")";
      out += '\n';
    }
    if (o_.raw) {
      out += hex_dump(m.data);
    } else if (d.value) {
      types::TextOptions to;
      to.max_array = o_.max_array;
      if (!o_.field.empty()) out += o_.field + ": ";
      out += types::to_text(*d.value, to);
    }
    return out;
  }

  std::string json(const RawMessage& m, std::int64_t now) const {
    const Decoded d = decode(m);
    std::string out = "{\"channel\":" + json_str(std::string(m.channel)) + ",\"recv_us\":" + std::to_string(now) +
                      ",\"size\":" + std::to_string(m.data.size());
    if (d.fingerprint) out += ",\"fingerprint\":\"" + hex_fingerprint(*d.fingerprint) + "\"";
    if (d.type) out += ",\"type\":" + json_str(d.type->full_name());
    if (o_.raw) out += ",\"raw\":\"" + hex_string(m.data) + "\"";
    if (!d.error.empty()) out += ",\"error\":" + json_str(d.error);
    if (d.value) {
      if (!o_.field.empty()) out += ",\"field\":" + json_str(o_.field);
      out += ",\"data\":" + types::to_json(*d.value);
    }
    return out + "}\n";
  }

  const EchoOptions& o_;
  const types::TypeRegistry& reg_;
  StopSignals& stop_;
  std::atomic<bool> done_{false};
  std::mutex mu_;
  std::uint64_t printed_ = 0;
  bool write_failed_ = false;
};

int run_echo() {
  const auto& o = g_echo;
  spdlog::set_level(spdlog::level::warn);
  std::shared_ptr<const ChannelMatcher> match;
  try {
    match = std::make_shared<ChannelMatcher>(o.channels, o.regex);
  } catch (const std::regex_error& e) {
    std::cerr << "lcmx echo: bad channel expression: " << e.what() << "\n";
    return 2;
  }
  types::TypeRegistry reg;
  if (!o.raw || !o.types.empty()) {
    try {
      reg = load_types(o.types);
    } catch (const types::Error& e) {
      std::cerr << "lcmx echo: " << e.what() << "\n";
      return 1;
    }
    if (reg.size() == 0 && !o.raw)
      std::cerr << "lcmx echo: no type path (--types DIR|FILE or LCMX_TYPES_PATH): messages show their "
                   "channel, size and fingerprint only (--raw: their bytes)\n";
  }
  StopSignals stop;
  Printer printer(o, reg, stop);
  std::optional<Tap> tap;
  try {
    SubscriberOptions so;
    so.queue_depth = o.queue_depth;
    so.policy = QueuePolicy::drop_oldest;
    tap.emplace(*o.g, "lcmx_echo", match, [&printer](const RawMessage& m) { printer.on_message(m); }, so);
  } catch (const std::exception& e) {
    std::cerr << "lcmx echo: " << e.what() << "\n";
    return 1;
  }
  // One write: the executor thread may already print messages on stdout (a terminal, or one
  // pipe for both), and a line written in pieces would be cut by them.
  const std::string listening =
      "lcmx echo: listening (" + (reg.size() ? std::to_string(reg.size()) + " types" : std::string("no types")) + ")\n";
  std::cerr << listening << std::flush;
  stop.wait(std::chrono::nanoseconds(-1));
  std::uint64_t drops = 0;
  for (const auto& [ch, st] : tap->stats()) drops += st.drops;
  tap.reset();  // no callback after this
  if (drops > 0 && !printer.write_failed())
    std::cerr << "lcmx echo: " << drops << " messages dropped (printing slower than they came)\n";
  return 0;
}

}  // namespace

Verb add_echo(CLI::App& app, const Globals& g) {
  g_echo.g = &g;
  auto* c = app.add_subcommand(
      "echo",
      "print the messages of channels, decoded with the .lcm files of the type path (every path: shm, "
      "bridges, other hosts, stock LCM programs)");
  c->add_option("channel", g_echo.channels,
                "channel names or globs (CAM_*, quote them for the shell); with --regex, regular expressions")
      ->required();
  c->add_flag("--regex", g_echo.regex, "CHANNEL arguments are regular expressions (ECMAScript, whole name)");
  c->add_option("-t,--types", g_echo.types,
                ".lcm file or directory (searched recursively; repeatable, or a ':' list); default LCMX_TYPES_PATH")
      ->allow_extra_args(false);
  c->add_flag("--json", g_echo.json,
              "one JSON object per message and line: {\"channel\", \"recv_us\" (receive time, µs since the "
              "epoch), \"size\", \"fingerprint\", \"type\", \"data\" (the message, complete) or \"error\"}");
  c->add_option("-n,--count", g_echo.count, "exit after this many messages (0: until SIGINT/SIGTERM)")
      ->check(non_negative_number());
  c->add_option("--field", g_echo.field, "print only this part of each message, e.g. pose.position[2] or points[0]");
  c->add_flag("--raw", g_echo.raw, "print the bytes in hex instead of decoding (no type path needed)");
  c->add_option("--max-array", g_echo.max_array, "text: elements shown per array before '... (N more)'; 0: all")
      ->capture_default_str();
  c->add_flag("--no-header", g_echo.no_header, "text: leave out the '--- channel time size type' line");
  c->add_option("--queue-depth", g_echo.queue_depth,
                "messages queued per channel (UDP, in-process) while printing; beyond it the oldest are dropped")
      ->check(CLI::Range(1, 1 << 20))
      ->capture_default_str();
  c->footer(
      "A message whose fingerprint no type of the type path has shows its channel, size and fingerprint; "
      "one that does not decode (truncated, garbage) shows why. Exit: 0 on SIGINT/SIGTERM or -n reached, "
      "1 for a bad type path, 2 for bad arguments.");
  return {c, [] { return run_echo(); }};
}

}  // namespace lcmx::cli
