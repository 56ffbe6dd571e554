// `lcmx monitor`: lcm-spy in the terminal (ncurses). One row per channel on every path (shm,
// UDP from other hosts, bridges, stock LCM programs): type, publishers, paths, Hz, jitter,
// bandwidth, drops, age of the last message. Sort, filter, pause; Enter opens the decoded
// latest message of a channel (live, foldable) with a sparkline of its rate.
// `--once` prints one snapshot (table or --json) without a terminal, for scripts.
//
// Light by construction: the receive callback only counts (and copies the bytes of the one
// opened channel); it is a drop-oldest subscriber (never slows a publisher); only the opened
// channel is decoded, at most once per redraw; redraws are bounded by --refresh.
// Threads: the node's executor runs the callback (Model::on_message); the main thread does the
// rest (keys, ticks, drawing). Signals: SIGINT/SIGTERM set a flag; SIGWINCH is ncurses's (KEY_RESIZE).
#include <curses.h>
#include <langinfo.h>
#include <signal.h>
#include <spdlog/spdlog.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <clocale>
#include <cstring>
#include <iostream>
#include <optional>
#include <sstream>
#include <thread>

#include "lcmx/core.hpp"
#include "log_common.hpp"
#include "monitor_cmds.hpp"
#include "monitor_model.hpp"
#include "tools_common.hpp"

namespace lcmx::cli {
namespace {

using monitor::Clock;
using monitor::Column;
using monitor::Model;
using monitor::Row;

struct MonitorOptions {
  std::vector<std::string> types;
  std::string filter;
  std::string sort = "channel";
  bool reverse = false;
  int refresh_ms = 250;
  bool once = false;
  bool json = false;
  double duration_s = 2.0;
  std::size_t queue_depth = 16;
  const Globals* g = nullptr;
};
MonitorOptions g_mon;

std::atomic<bool> g_mon_stop{false};
extern "C" void on_monitor_signal(int) { g_mon_stop.store(true); }

std::optional<Column> column_from(const std::string& s) {
  for (int i = 0; i < monitor::kColumns; ++i) {
    const auto c = static_cast<Column>(i);
    std::string n = monitor::column_name(c);
    for (auto& ch : n) ch = static_cast<char>(std::tolower(static_cast<unsigned char>(ch)));
    if (n == s) return c;
  }
  return std::nullopt;
}

std::string fixed(double v, const char* f) { return fmt(f, v); }
std::string age_text(double a) { return a < 0 ? "-" : (a < 100 ? fmt("%.1fs", a) : fmt("%.0fs", a)); }

// ---- the terminal ----

// RAII: curses on, and off (terminal restored) on every exit path.
struct Screen {
  Screen() {
    ::setenv("ESCDELAY", "25", 0);
    initscr();
    cbreak();
    noecho();
    keypad(stdscr, TRUE);
    curs_set(0);
    timeout(50);
  }
  ~Screen() { endwin(); }
  Screen(const Screen&) = delete;
  Screen& operator=(const Screen&) = delete;
};

// `s` cut or padded to exactly `w` columns (a cut one ends with '~').
std::string cell(const std::string& s, int w) {
  if (w <= 0) return "";
  const auto uw = static_cast<std::size_t>(w);
  if (s.size() > uw) return s.substr(0, uw - 1) + "~";
  return s + std::string(uw - s.size(), ' ');
}
std::string rcell(const std::string& s, int w) {
  if (w <= 0) return "";
  const auto uw = static_cast<std::size_t>(w);
  if (s.size() > uw) return s.substr(0, uw - 1) + "~";
  return std::string(uw - s.size(), ' ') + s;
}

void put(int y, int x, const std::string& s, attr_t a = A_NORMAL) {
  if (y < 0 || y >= LINES || x >= COLS) return;
  attron(a);
  mvaddnstr(y, x, s.c_str(), COLS - x);
  attroff(a);
}

class Ui {
 public:
  Ui(Model& m, const types::TypeRegistry* reg, bool utf8) : m_(m), reg_(reg), utf8_(utf8) {}

  // Handles one key; returns false to quit.
  bool key(int k) {
    if (editing_) return edit_key(k), true;
    if (k == 'q' || k == 'Q') return false;
    if (k == 'p' || k == 'P') {
      paused_ = !paused_;
      return true;
    }
    if (!m_.opened().empty()) return detail_key(k), true;
    const int n = static_cast<int>(rows_.size());
    switch (k) {
      case KEY_UP: case 'k': sel_ = std::max(0, sel_ - 1); break;
      case KEY_DOWN: case 'j': sel_ = std::min(std::max(0, n - 1), sel_ + 1); break;
      case KEY_PPAGE: sel_ = std::max(0, sel_ - page()); break;
      case KEY_NPAGE: sel_ = std::min(std::max(0, n - 1), sel_ + page()); break;
      case KEY_HOME: sel_ = 0; break;
      case KEY_END: sel_ = std::max(0, n - 1); break;
      case 's': m_.set_sort(static_cast<Column>((static_cast<int>(m_.sort_column()) + 1) % monitor::kColumns),
                            m_.descending()); refresh_rows(); break;
      case 'S': m_.set_sort(static_cast<Column>((static_cast<int>(m_.sort_column()) + monitor::kColumns - 1) %
                                                monitor::kColumns), m_.descending()); refresh_rows(); break;
      case 'r': m_.set_sort(m_.sort_column(), !m_.descending()); refresh_rows(); break;
      case '/': editing_ = true; edit_ = m_.filter(); break;
      case '\n': case '\r': case KEY_ENTER: case KEY_RIGHT:
        if (sel_ < n) {
          m_.open(rows_[static_cast<std::size_t>(sel_)].channel);
          toggled_.clear();
          value_.reset();
          lines_.clear();
          cursor_ = top_ = 0;
          note_ = "waiting for the next message";
        }
        break;
      default:
        if (k >= '1' && k <= '0' + monitor::kColumns) {
          const auto c = static_cast<Column>(k - '1');
          m_.set_sort(c, c == m_.sort_column() ? !m_.descending() : m_.descending());
          refresh_rows();
        }
    }
    return true;
  }

  // Periodic: new rows (unless paused) and, in the detail view, the latest message decoded.
  void update(Clock::time_point now) {
    if (paused_) return;
    now_ = now;
    refresh_rows();
    if (!m_.opened().empty())
      if (auto bytes = m_.take_latest()) decode(*bytes);
  }

  void draw() {
    erase();
    if (COLS < 40 || LINES < 8) {
      put(0, 0, "terminal too small (40x8 at least); q quits");
      refresh();
      return;
    }
    if (m_.opened().empty()) draw_list();
    else draw_detail();
    refresh();
  }

 private:
  int page() const { return std::max(1, LINES - 4); }

  void refresh_rows() {
    std::string selected = sel_ < static_cast<int>(rows_.size()) ? rows_[static_cast<std::size_t>(sel_)].channel : "";
    rows_ = m_.rows(now_);
    // The selection follows its channel when the order changes.
    for (std::size_t i = 0; i < rows_.size(); ++i)
      if (rows_[i].channel == selected) sel_ = static_cast<int>(i);
    sel_ = std::min(sel_, std::max(0, static_cast<int>(rows_.size()) - 1));
  }

  void edit_key(int k) {
    if (k == 27) {
      editing_ = false;
    } else if (k == '\n' || k == '\r' || k == KEY_ENTER) {
      editing_ = false;
      try {
        m_.set_filter(edit_);
        status_.clear();
        sel_ = 0;
        refresh_rows();
      } catch (const std::regex_error& e) {
        status_ = "bad filter expression '" + edit_ + "': " + e.what();
      }
    } else if (k == KEY_BACKSPACE || k == 127 || k == 8) {
      if (!edit_.empty()) edit_.pop_back();
    } else if (k >= 32 && k < 127) {
      edit_ += static_cast<char>(k);
    }
  }

  void detail_key(int k) {
    const int n = static_cast<int>(lines_.size());
    switch (k) {
      case 27: case KEY_LEFT: case KEY_BACKSPACE: case 127: case 8:
        m_.close();
        refresh_rows();
        break;
      case KEY_UP: case 'k': cursor_ = std::max(0, cursor_ - 1); break;
      case KEY_DOWN: case 'j': cursor_ = std::min(std::max(0, n - 1), cursor_ + 1); break;
      case KEY_PPAGE: cursor_ = std::max(0, cursor_ - page()); break;
      case KEY_NPAGE: cursor_ = std::min(std::max(0, n - 1), cursor_ + page()); break;
      case KEY_HOME: cursor_ = 0; break;
      case KEY_END: cursor_ = std::max(0, n - 1); break;
      case '\n': case '\r': case KEY_ENTER: case ' ':
        if (cursor_ < n && lines_[static_cast<std::size_t>(cursor_)].foldable) {
          const auto& p = lines_[static_cast<std::size_t>(cursor_)].path;
          if (!toggled_.erase(p)) toggled_.insert(p);
          rebuild();
        }
        break;
      default: break;
    }
  }

  void decode(const std::vector<std::byte>& bytes) {
    size_ = bytes.size();
    const auto fp = types::message_fingerprint(bytes.data(), bytes.size());
    const types::StructType* t = (fp && reg_) ? reg_->find(*fp) : nullptr;
    if (t == nullptr) {
      note_ = fp ? "type unknown (fingerprint " + hex(*fp) +
                       "): give its .lcm with --types or LCMX_TYPES_PATH; raw bytes:"
                 : "message shorter than a fingerprint; raw bytes:";
      const auto* p = reinterpret_cast<const std::uint8_t*>(bytes.data());
      value_ = types::Value(types::Bytes(p, p + bytes.size()));
    } else {
      try {
        value_ = types::decode(*t, bytes.data(), bytes.size());
        note_.clear();
      } catch (const types::Error& e) {
        note_ = std::string("cannot decode as ") + t->full_name() + ": " + e.what();
        const auto* p = reinterpret_cast<const std::uint8_t*>(bytes.data());
        value_ = types::Value(types::Bytes(p, p + bytes.size()));
      }
    }
    rebuild();
  }

  static std::string hex(std::uint64_t v) {
    char b[24];
    std::snprintf(b, sizeof b, "0x%016llx", static_cast<unsigned long long>(v));
    return b;
  }

  void rebuild() {
    if (!value_) return;
    // A raw-bytes view starts open; a decoded message with its defaults.
    lines_ = monitor::tree_lines(*value_, toggled_);
    cursor_ = std::min(cursor_, std::max(0, static_cast<int>(lines_.size()) - 1));
  }

  void header(const std::string& left) {
    std::string right;
    if (paused_) right = "  PAUSED";
    put(0, 0, cell(left + right, COLS), A_BOLD);
  }

  void draw_list() {
    std::string h = "lcmx monitor  " + std::to_string(rows_.size()) + " channels  sort: " +
                    monitor::column_name(m_.sort_column()) + (m_.descending() ? " (desc)" : "");
    if (!m_.filter().empty()) h += "  filter: /" + m_.filter() + "/";
    header(h);
    // Columns: fixed numeric ones; the rest shared by channel, type and publishers, each as
    // wide as its longest entry when there is room.
    const int wz = 6, wj = 6, wb = 6, wd = 5, wa = 5, wp = 5;
    const int fixed_w = wz + wj + wb + wd + wa + wp + 8;
    const int flex = std::max(20, COLS - fixed_w);
    int lc = 7, lt = 4;
    for (const auto& r : rows_) {
      lc = std::max(lc, static_cast<int>(r.channel.size()));
      lt = std::max(lt, static_cast<int>(r.type.size()));
    }
    const int wc = std::clamp(lc, 8, flex / 2);
    const int wt = std::clamp(lt, 6, (flex - wc) * 3 / 5);
    const int wpub = std::max(1, flex - wc - wt);
    const int widths[] = {wc, wt, wpub, wp, wz, wj, wb, wd, wa};
    const char* titles[] = {"CHANNEL", "TYPE", "PUBLISHERS", "PATH", "HZ", "JIT ms", "B/s", "DROPS", "AGE"};
    int x = 0;
    for (int i = 0; i < monitor::kColumns; ++i) {
      const bool right = i >= 4;
      const attr_t a = (i == static_cast<int>(m_.sort_column())) ? A_REVERSE | A_BOLD : A_BOLD;
      put(1, x, right ? rcell(titles[i], widths[i]) : cell(titles[i], widths[i]), a);
      x += widths[i] + 1;
    }
    const int first_row = 2, last_row = LINES - 3;
    const int visible = last_row - first_row + 1;
    if (sel_ < top_) top_ = sel_;
    if (sel_ >= top_ + visible) top_ = sel_ - visible + 1;
    top_ = std::max(0, std::min(top_, std::max(0, static_cast<int>(rows_.size()) - visible)));
    for (int i = 0; i < visible && top_ + i < static_cast<int>(rows_.size()); ++i) {
      const Row& r = rows_[static_cast<std::size_t>(top_ + i)];
      // Names from beacons and datagrams: escaped (safe_text.hpp) before they are cut to width.
      std::string line = cell(printable(r.channel), wc) + " " + cell(printable(r.type), wt) + " " +
                         cell(printable(r.publishers), wpub) + " " + cell(printable(r.paths), wp) + " " + rcell(r.age_s < 0 ? "-" : fixed(r.hz, "%.1f"), wz) + " " +
                         rcell(r.age_s < 0 ? "-" : fixed(r.jitter_ms, "%.2f"), wj) + " " +
                         rcell(monitor::human(r.bytes_per_s), wb) + " " + rcell(std::to_string(r.drops), wd) + " " +
                         rcell(age_text(r.age_s), wa);
      put(first_row + i, 0, line, top_ + i == sel_ ? A_REVERSE : (r.drops > 0 ? A_BOLD : A_NORMAL));
    }
    if (rows_.empty()) put(first_row, 0, m_.filter().empty() ? "no channels yet" : "no channel matches the filter");
    footer("q:quit Up/Dn:select Enter:open 1-9/s:sort column r:reverse /:filter p:pause");
  }

  void draw_detail() {
    const std::string& ch = m_.opened();
    const Row* row = nullptr;
    for (const auto& r : rows_)
      if (r.channel == ch) row = &r;
    std::string h = printable(ch);
    if (row) h += "  " + printable(row->type) + "  " + fixed(row->hz, "%.1f") + " Hz  " + std::to_string(row->messages) +
                  " msgs  last " + std::to_string(size_) + " B  age " + age_text(row->age_s);
    header(h);
    const auto hist = m_.rate_history(ch);
    double top = 0;
    for (double v : hist) top = std::max(top, v);
    const std::string label = "rate (max " + fixed(top, "%.1f") + " Hz) ";
    put(1, 0, label);
    const int sw = std::max(0, COLS - static_cast<int>(label.size()) - 1);
    put(1, static_cast<int>(label.size()), monitor::sparkline(hist, static_cast<std::size_t>(sw), utf8_));
    int y = 2;
    if (!note_.empty()) put(y++, 0, printable(note_), A_DIM);
    const int first = y, visible = LINES - 2 - first + 1 - 1;
    if (cursor_ < top_) top_ = cursor_;
    if (cursor_ >= top_ + visible) top_ = cursor_ - visible + 1;
    top_ = std::max(0, top_);
    for (int i = 0; i < visible && top_ + i < static_cast<int>(lines_.size()); ++i) {
      const auto& l = lines_[static_cast<std::size_t>(top_ + i)];
      std::string s = std::string(static_cast<std::size_t>(l.depth) * 2, ' ') +
                      (l.foldable ? (l.folded ? "+ " : "- ") : "  ") + l.text;
      put(first + i, 0, cell(s, COLS), top_ + i == cursor_ ? A_REVERSE : A_NORMAL);
    }
    footer("q:quit  Esc/Left:back  Up/Dn:move  Enter/Space:fold  p:pause");
  }

  void footer(const std::string& keys) {
    if (editing_) put(LINES - 2, 0, cell("filter (regex, Enter applies, Esc cancels): " + edit_, COLS), A_BOLD);
    else if (!status_.empty()) put(LINES - 2, 0, cell(status_, COLS), A_BOLD);
    put(LINES - 1, 0, cell(keys, COLS), A_REVERSE);
  }

  Model& m_;
  const types::TypeRegistry* reg_;
  bool utf8_;
  Clock::time_point now_ = Clock::now();
  std::vector<Row> rows_;
  int sel_ = 0, top_ = 0;
  bool paused_ = false, editing_ = false;
  std::string edit_, status_;
  // Detail view.
  std::optional<types::Value> value_;
  std::vector<monitor::TreeLine> lines_;
  std::set<std::string> toggled_;
  int cursor_ = 0;
  std::size_t size_ = 0;
  std::string note_;
};

void print_snapshot(const std::vector<Row>& rows, bool json) {
  if (json) {
    std::ostringstream j;
    j << "{\"channels\":[";
    for (std::size_t i = 0; i < rows.size(); ++i) {
      const auto& r = rows[i];
      j << (i ? "," : "") << "{\"channel\":" << json_str(r.channel) << ",\"type\":" << json_str(r.type)
        << ",\"publishers\":" << json_str(r.publishers) << ",\"paths\":" << json_str(r.paths)
        << ",\"hz\":" << fmt("%.3f", r.hz) << ",\"jitter_ms\":" << fmt("%.3f", r.jitter_ms)
        << ",\"bytes_per_s\":" << fmt("%.1f", r.bytes_per_s) << ",\"drops\":" << r.drops
        << ",\"messages\":" << r.messages << ",\"last_size\":" << r.last_size << ",\"age_s\":"
        << (r.age_s < 0 ? std::string("null") : fmt("%.3f", r.age_s)) << "}";
    }
    j << "]}";
    std::cout << j.str() << std::endl;
    return;
  }
  char line[512];
  std::snprintf(line, sizeof line, "%-32s %-24s %-28s %-8s %8s %8s %8s %6s %7s\n", "CHANNEL", "TYPE", "PUBLISHERS",
                "PATH", "HZ", "JIT_MS", "BW_B/s", "DROPS", "AGE");
  std::cout << line;
  for (const auto& r : rows) {
    std::snprintf(line, sizeof line, "%-32s %-24s %-28s %-8s %8.1f %8.2f %8s %6llu %7s\n", printable(r.channel).c_str(),
                  printable(r.type).c_str(), r.publishers.empty() ? "-" : printable(r.publishers).c_str(),
                  r.paths.empty() ? "-" : printable(r.paths).c_str(), r.hz, r.jitter_ms, monitor::human(r.bytes_per_s).c_str(),
                  static_cast<unsigned long long>(r.drops), age_text(r.age_s).c_str());
    std::cout << line;
  }
}

int run_monitor() {
  const auto& o = g_mon;
  spdlog::set_level(spdlog::level::err);
  if (o.json && !o.once) {
    std::cerr << "lcmx monitor: --json prints a snapshot: give --once too\n";
    return 2;
  }
  if (!o.once && (!::isatty(STDIN_FILENO) || !::isatty(STDOUT_FILENO))) {
    std::cerr << "lcmx monitor: needs a terminal (use --once [--json] for a snapshot in scripts)\n";
    return 2;
  }
  const auto sort = column_from(o.sort);
  if (!sort) {
    std::cerr << "lcmx monitor: unknown --sort column '" << o.sort
              << "' (channel, type, publishers, path, hz, jitter, bandwidth, drops, age)\n";
    return 2;
  }
  types::TypeRegistry registry;
  try {
    const auto paths = types::TypeRegistry::paths_or_env(o.types);
    if (!paths.empty()) registry = types::TypeRegistry::load(paths);
  } catch (const types::Error& e) {
    std::cerr << "lcmx monitor: type path: " << e.what() << "\n";
    return 2;
  }
  Model model(&registry);
  model.set_sort(*sort, o.reverse);
  try {
    model.set_filter(o.filter);
  } catch (const std::regex_error& e) {
    std::cerr << "lcmx monitor: bad --filter expression: " << e.what() << "\n";
    return 2;
  }

  struct sigaction sa{};
  sa.sa_handler = on_monitor_signal;
  sigemptyset(&sa.sa_mask);
  ::sigaction(SIGINT, &sa, nullptr);
  ::sigaction(SIGTERM, &sa, nullptr);

  std::optional<Observer> obs;
  std::optional<Runtime> rt;
  std::optional<Node> node;
  ChannelSubscription sub;
  try {
    obs.emplace(*o.g);
    rt.emplace(Runtime::create(runtime_options(*o.g)));
    node.emplace(rt->create_node("lcmx_monitor"));
    SubscriberOptions so;
    so.queue_depth = o.queue_depth;
    so.policy = QueuePolicy::drop_oldest;  // never slows a publisher
    sub = node->subscribe_channels([](const std::string&) { return true; },
                                   [&model](const RawMessage& m) { model.on_message(m.channel, m.data, Clock::now()); },
                                   so);
    obs->query();
  } catch (const std::exception& e) {
    std::cerr << "lcmx monitor: " << e.what() << "\n";
    return 1;
  }
  const std::uint64_t self = rt->participant_id();
  auto refresh_model = [&](Clock::time_point now) {
    model.tick(now);
    model.set_topology(obs->participants(), self);
    model.set_stats(sub.stats());
  };

  const auto tick_every = std::chrono::milliseconds(500);
  if (o.once) {
    const auto start = Clock::now();
    const auto end = start + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(o.duration_s));
    auto next = start + tick_every;
    while (!g_mon_stop.load() && Clock::now() < end) {
      std::this_thread::sleep_until(std::min(next, end));
      if (Clock::now() >= next) {
        refresh_model(Clock::now());
        next += tick_every;
      }
    }
    refresh_model(Clock::now());
    print_snapshot(model.rows(Clock::now()), o.json);
    return 0;
  }

  std::setlocale(LC_ALL, "");
  const bool utf8 = std::strcmp(nl_langinfo(CODESET), "UTF-8") == 0;
  {
    Screen screen;
    Ui ui(model, &registry, utf8);
    const auto redraw_every = std::chrono::milliseconds(o.refresh_ms);
    auto next_tick = Clock::now() + tick_every;
    auto next_draw = Clock::now();
    bool dirty = true;
    while (!g_mon_stop.load()) {
      const int k = getch();  // waits up to 50 ms
      const auto now = Clock::now();
      if (k == KEY_RESIZE) {
        clear();
        dirty = true;
      } else if (k != ERR) {
        if (!ui.key(k)) break;
        dirty = true;
      }
      if (now >= next_tick) {
        refresh_model(now);
        next_tick = now + tick_every;
      }
      if (now >= next_draw) {
        ui.update(now);
        next_draw = now + redraw_every;
        dirty = true;
      }
      if (dirty) {
        ui.draw();
        dirty = false;
      }
    }
  }  // endwin
  sub.reset();
  node.reset();
  rt.reset();
  return 0;
}

}  // namespace

Verb add_monitor(CLI::App& app, const Globals& g) {
  g_mon.g = &g;
  auto* c = app.add_subcommand(
      "monitor",
      "lcm-spy in the terminal: every channel (shm, UDP, bridges, stock LCM) with type, publishers, "
      "paths, Hz, jitter, bandwidth, drops, age; Enter shows the decoded latest message");
  c->add_option("--types", g_mon.types,
                "'.lcm' files or directories (searched recursively) to decode with; default LCMX_TYPES_PATH")
      ->type_name("PATH")
      ->allow_extra_args(false);  // one value per --types (repeatable), as the other verbs
  c->add_option("--filter", g_mon.filter, "show channels whose name contains a match of this regex (case-insensitive)");
  c->add_option("--sort", g_mon.sort, "sort by channel, type, publishers, path, hz, jitter, bandwidth, drops or age")
      ->capture_default_str();
  c->add_flag("--reverse", g_mon.reverse, "sort descending");
  c->add_option("--refresh", g_mon.refresh_ms, "redraw every MS milliseconds (at most)")
      ->check(CLI::Range(50, 10000))
      ->capture_default_str();
  c->add_option("--queue-depth", g_mon.queue_depth, "per channel queue before the oldest message is dropped")
      ->check(CLI::Range(1, 1 << 16))
      ->capture_default_str();
  c->add_flag("--once", g_mon.once, "no terminal: listen for --duration seconds, print the table and exit");
  c->add_flag("--json", g_mon.json, "with --once: the table as one JSON object");
  c->add_option("--duration", g_mon.duration_s, "with --once: how long to listen, in seconds")
      ->check(CLI::Range(0.1, 3600.0))
      ->capture_default_str();
  c->footer(
      "Keys (shown on screen): Up/Down select, Enter open the channel's latest message (Enter/Space "
      "fold, Esc/Left back), s/S or 1-9 sort column, r reverse, / filter (regex), p pause, q or "
      "Ctrl-C quit.");
  return {c, [] { return run_monitor(); }};
}

}  // namespace lcmx::cli
