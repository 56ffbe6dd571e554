// `lcmx monitor`'s model, apart from the terminal (monitor_cmd.cpp draws it with ncurses), so
// it is unit-tested without one (test/tools/monitor_model_test.cpp): per-channel statistics
// from raw arrivals, the channel table (type, publishers, paths, Hz, jitter, bandwidth, drops,
// age) sorted and filtered, the latest message of the one opened channel, and the foldable
// tree of a decoded message.
//
// Threads: on_message() may be called from any thread (the node's executor); every other
// member from one thread (the UI). The model holds one mutex, taken briefly by both.
// Errors: none thrown by on_message(); set_filter() throws std::regex_error for a bad expression.
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <deque>
#include <map>
#include <mutex>
#include <optional>
#include <regex>
#include <set>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "lcmx/core/stats.hpp"
#include "lcmx/discovery/discovery.hpp"
#include "lcmx/types/types.hpp"

namespace lcmx::cli::monitor {

using Clock = std::chrono::steady_clock;

enum class Column { channel, type, publishers, path, hz, jitter, bandwidth, drops, age };
constexpr int kColumns = 9;
const char* column_name(Column c);

// One line of the table, as numbers (the view formats them).
struct Row {
  std::string channel;
  std::string type;        // package-qualified from the type path, else the beacon's, else 0x<fingerprint hex>
  std::string publishers;  // "process[pid]@host" of lcmx publishers, "LCM sender" for stock ones
  std::string paths;       // paths of our pairs: "shm", "udp,shm", ...
  double hz = 0;           // messages per second over the window
  double jitter_ms = 0;    // standard deviation of the inter-arrival time over the window
  double bytes_per_s = 0;
  std::uint64_t drops = 0;
  std::uint64_t messages = 0;  // received since the monitor started
  std::size_t last_size = 0;
  double age_s = -1;  // since the last message; -1: none yet (announced, nothing received)
};

class Model {
 public:
  // `registry` (may be null) resolves fingerprints to type names; it must outlive the model.
  // `window`: how far back rates and jitter look; `history`: samples kept for the sparkline.
  // Samples before the first tick start at `start`.
  explicit Model(const types::TypeRegistry* registry, Clock::duration window = std::chrono::seconds(2),
                 std::size_t history = 60, Clock::time_point start = Clock::now());

  // A message arrived (any thread). Copies the bytes only for the opened channel.
  void on_message(std::string_view channel, std::span<const std::byte> data, Clock::time_point t);

  // Closes the current sample period at `now` (call every ~0.5 s): rates over the window and
  // one sparkline sample per channel.
  void tick(Clock::time_point now);

  // Other participants' beacons (ours, `self`, left out): publishers and their types per topic.
  // Topics announced but silent get rows too (age -1).
  void set_topology(const std::vector<discovery::Participant>& participants, std::uint64_t self);
  // Our channel subscription's statistics: drops and paths per channel.
  void set_stats(const std::vector<std::pair<std::string, SubscriberStats>>& stats);

  // The table, filtered (regex_search on the channel name, case-insensitive; empty: all) and
  // sorted by `sort` (ties by channel name).
  std::vector<Row> rows(Clock::time_point now) const;
  void set_sort(Column c, bool descending);
  Column sort_column() const { return sort_; }
  bool descending() const { return descending_; }
  void set_filter(const std::string& expression);  // throws std::regex_error
  const std::string& filter() const { return filter_text_; }

  // The opened channel: only its messages are kept (the latest) for decoding.
  void open(const std::string& channel);
  void close();
  const std::string& opened() const { return opened_; }
  // The latest message of the opened channel if one arrived since the previous call.
  std::optional<std::vector<std::byte>> take_latest();
  // Rate samples (Hz) of a channel, oldest first.
  std::vector<double> rate_history(const std::string& channel) const;

  // Type name for a fingerprint: the type path's, else the beacons' for `channel`, else hex.
  std::string type_name(const std::string& channel, std::optional<std::uint64_t> fingerprint) const;

 private:
  struct Sample {
    Clock::time_point start, end;
    std::uint64_t n = 0, bytes = 0, intervals = 0;
    double sum_dt = 0, sum_dt2 = 0;  // seconds
  };
  struct Chan {
    // Since the last tick (written by on_message).
    Sample open;
    std::uint64_t messages = 0;
    std::size_t last_size = 0;
    std::optional<std::uint64_t> fingerprint;
    std::optional<Clock::time_point> last;
    // Closed samples within the window, and the sparkline.
    std::deque<Sample> window;
    std::deque<double> history;
    // From beacons / our stats.
    std::set<std::string> publishers, beacon_types, paths;
    std::uint64_t drops = 0;
    bool announced = false;  // in the latest topology
  };
  Chan& chan_locked(std::string_view channel);

  const types::TypeRegistry* registry_;
  Clock::duration window_;
  std::size_t history_;
  mutable std::mutex mu_;
  std::map<std::string, Chan, std::less<>> chans_;
  Clock::time_point created_;
  std::optional<Clock::time_point> last_tick_;
  Column sort_ = Column::channel;
  bool descending_ = false;
  std::string filter_text_;
  std::optional<std::regex> filter_;
  std::string opened_;
  std::vector<std::byte> latest_;
  bool latest_new_ = false;
};

// ---- the decoded message as foldable lines ----

struct TreeLine {
  int depth = 0;
  std::string path;  // "pose.position[2]": identifies the line across updates
  std::string text;  // "name: value", "name: struct pkg.t", "name: int32_t[100]"
  bool foldable = false;
  bool folded = false;
};

// Lines of a decoded message. Nested structs are open and arrays of more than `fold_over`
// elements (and byte arrays) folded, unless their path is in `toggled` (which flips that).
// An open array shows at most `max_elements` elements, then "... N more".
std::vector<TreeLine> tree_lines(const types::Value& value, const std::set<std::string>& toggled,
                                 std::size_t fold_over = 8, std::size_t max_elements = 1000);

// A sparkline of `samples` (the last `width` of them), scaled to the largest: UTF-8 block
// characters when `utf8`, else ASCII " .:-=+*#".
std::string sparkline(const std::vector<double>& samples, std::size_t width, bool utf8);

// "12.3k", "4.5M" (bytes/s and sizes).
std::string human(double v);

}  // namespace lcmx::cli::monitor
