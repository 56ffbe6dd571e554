// `lcmx record`: an lcmx participant that writes every message it receives (shared memory,
// bridges, UDP from other hosts, stock LCM programs on both groups) into an LCM event log,
// byte-compatible with lcm-logger's.
//
// Threads: the node's executor runs the receive callback, which only copies the message into
// a bounded queue (never blocks a publisher: shm and UDP queues drop the oldest, counted; a
// full recorder queue drops the new message, counted); the writer thread writes the queue
// to the file at least every --flush-interval, splits and rotates; the main thread handles
// signals (flags set by handlers), the status line and the summary.
#include <fcntl.h>
#include <pthread.h>
#include <sched.h>
#include <signal.h>
#include <spdlog/spdlog.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cstring>
#include <atomic>
#include <condition_variable>
#include <deque>
#include <iostream>
#include <map>
#include <mutex>
#include <optional>
#include <set>
#include <sstream>
#include <thread>

#include "lcmx/core.hpp"
#include "lcmx/log/eventlog.hpp"
#include "log_cmds.hpp"
#include "log_common.hpp"

namespace lcmx::cli {
namespace {

struct RecordOptions {
  std::string file;
  std::string channel = ".*";
  std::vector<std::string> exclude;
  bool increment = false;
  bool force = false;
  bool append = false;
  bool strftime_name = false;
  int rotate = 0;
  double split_mb = 0;
  double split_s = 0;
  double max_duration_s = 0;
  int flush_ms = 100;
  double max_unwritten_mb = 256;
  std::size_t queue_depth = 1024;
  int rt_priority = 0;
  bool quiet = false;
  bool json = false;
  const Globals* g = nullptr;  // read when the verb runs (filled by the parse)
};
RecordOptions g_rec;

std::atomic<bool> g_stop{false};
std::atomic<bool> g_rotate{false};
extern "C" void on_stop_signal(int) { g_stop.store(true); }
extern "C" void on_hup_signal(int) { g_rotate.store(true); }

bool exists(const std::string& p) {
  struct stat st{};
  return ::stat(p.c_str(), &st) == 0;
}

std::string apply_strftime(const std::string& pattern) {
  const std::time_t t = std::time(nullptr);
  std::tm tm{};
  localtime_r(&t, &tm);
  std::vector<char> buf(pattern.size() * 4 + 256);
  const std::size_t n = std::strftime(buf.data(), buf.size(), pattern.c_str(), &tm);
  return n == 0 ? pattern : std::string(buf.data(), n);
}

// File names as lcm-logger: FILE; with --increment FILE.NN (first unused NN from 00); with
// --rotate N always FILE.0, older files moved to FILE.1 … FILE.N-1 (the oldest deleted).
class Namer {
 public:
  explicit Namer(const RecordOptions& o) : o_(o) {
    use_default_ = o.file.empty();
    increment_ = o.rotate == 0 && (use_default_ || o.increment || o.split_mb > 0 || o.split_s > 0);
  }
  bool increment() const { return increment_ || o_.rotate > 0; }
  std::string next() {
    std::string base = use_default_ ? "lcmxlog-%Y-%m-%d" : o_.file;
    if (use_default_ || o_.strftime_name) base = apply_strftime(base);
    if (o_.rotate > 0) {
      for (int k = o_.rotate - 1; k >= 0; --k) {
        const std::string from = base + "." + std::to_string(k);
        if (!exists(from)) continue;
        if (k == o_.rotate - 1) ::unlink(from.c_str());
        else ::rename(from.c_str(), (base + "." + std::to_string(k + 1)).c_str());
      }
      return base + ".0";
    }
    if (!increment_) return base;
    if (base != last_base_) last_base_ = base, index_ = 0;
    for (;; ++index_) {
      char suffix[16];
      std::snprintf(suffix, sizeof suffix, ".%02d", index_);
      const std::string name = base + suffix;
      if (!exists(name)) {
        ++index_;
        return name;
      }
    }
  }

 private:
  const RecordOptions& o_;
  bool use_default_ = false, increment_ = false;
  std::string last_base_;
  int index_ = 0;
};

struct Item {
  std::int64_t ts;
  const std::string* channel;  // interned in Recorder::names (never freed while recording)
  std::vector<std::byte> data;
};

struct ChannelCount {
  std::uint64_t messages = 0, bytes = 0, recorder_drops = 0;  // messages, bytes: in the file
  std::uint64_t unwritten = 0;  // received, then lost to a failed write (disk full...)
};

class Recorder {
 public:
  explicit Recorder(const RecordOptions& o) : o_(o), namer_(o) {}

  // Executor thread. Copies the message into the queue (a recycled buffer when one fits).
  void on_message(const RawMessage& m) {
    const std::int64_t ts = wall_us();
    std::vector<std::byte> buf;
    std::unique_lock lock(mu_);
    auto& name = intern_locked(m.channel);
    auto& c = counts_[name];
    if (queued_bytes_ + m.data.size() > max_queued_) {
      ++c.recorder_drops;
      return;
    }
    if (!pool_.empty()) {
      buf = std::move(pool_.back());
      pool_.pop_back();
    }
    lock.unlock();
    buf.assign(m.data.begin(), m.data.end());  // the one copy, out of the lock
    lock.lock();
    queued_bytes_ += buf.size();
    ++c.messages;
    c.bytes += buf.size();
    queue_.push_back({ts, &name, std::move(buf)});
    if (queued_bytes_ >= (4u << 20)) cv_.notify_one();
  }

  // Picks the first file's name and mode, creating nothing (so a recording that fails to start
  // leaves no file behind). Throws eventlog::Error if the name is taken and no option says what
  // to do with it.
  void choose_first() {
    if (o_.append) {
      first_ = o_.file.empty() ? namer_.next() : (o_.strftime_name ? apply_strftime(o_.file) : o_.file);
      first_mode_ = eventlog::OpenMode::append;
    } else {
      first_ = namer_.next();
      if (o_.force && !namer_.increment()) first_mode_ = eventlog::OpenMode::overwrite;
      else if (exists(first_))
        throw eventlog::Error("'" + first_ + "' exists: give --force to overwrite, --append to add to it, or --increment");
    }
  }

  // Opens the file choose_first() picked. Throws eventlog::Error.
  void open_first() {
    writer_.emplace(eventlog::Writer::open(first_, first_mode_));
    file_start_ = std::chrono::steady_clock::now();
    files_.push_back(first_);
  }

  void start_writer() { thread_ = std::thread([this] { writer_loop(); }); }
  void stop_writer() {
    {
      std::lock_guard lock(mu_);
      stopping_ = true;
    }
    cv_.notify_one();
    if (thread_.joinable()) thread_.join();
  }

  struct Snapshot {
    std::map<std::string, ChannelCount> counts;
    std::uint64_t written_bytes = 0;
    std::string file;
    std::string error;
  };
  Snapshot snapshot() {
    Snapshot s;
    std::lock_guard lock(mu_);
    for (auto& [name, c] : counts_) s.counts[name] = c;
    s.written_bytes = written_bytes_;
    s.file = files_.empty() ? "" : files_.back();
    s.error = error_;
    return s;
  }
  std::vector<std::string> files() {
    std::lock_guard lock(mu_);
    return files_;
  }
  bool failed() {
    std::lock_guard lock(mu_);
    return !error_.empty();
  }

 private:
  const std::string& intern_locked(std::string_view channel) {
    auto it = names_.find(channel);
    if (it == names_.end()) it = names_.emplace(std::string(channel)).first;
    return *it;
  }

  // The next file: FILE.NN+1, or (no --increment: SIGHUP after logrotate moved FILE) FILE
  // again, appended to if it is still there.
  void rotate() {
    const std::string current = writer_->path();
    writer_->close();
    confirm();  // all of it
    writer_.reset();
    confirmed_out_ = 0;
    if (namer_.increment())
      writer_.emplace(eventlog::Writer::open(namer_.next(), eventlog::OpenMode::create));
    else
      writer_.emplace(eventlog::Writer::open(current, eventlog::OpenMode::append));
    file_start_ = std::chrono::steady_clock::now();
    std::lock_guard lock(mu_);
    files_.push_back(writer_->path());
  }

  void writer_loop() {
    std::deque<Item> batch;
    std::vector<std::vector<std::byte>> used;
    bool last = false;
    while (!last) {
      {
        std::unique_lock lock(mu_);
        cv_.wait_for(lock, std::chrono::milliseconds(o_.flush_ms),
                     [&] { return stopping_ || queued_bytes_ >= (4u << 20); });
        last = stopping_;
        batch.swap(queue_);
        queued_bytes_ = 0;
        for (auto& b : used)
          if (pool_.size() < 64 && b.capacity() > 0) pool_.push_back(std::move(b));
        used.clear();
      }
      for (const auto& it : batch) unconfirmed_.push_back({it.channel, it.data.size()});
      try {
        if (!writer_) {  // a write failed earlier: the rest is lost
          count_unwritten();
          batch.clear();
          continue;
        }
        for (auto& it : batch) {
          writer_->write(it.ts, *it.channel, it.data);
          used.push_back(std::move(it.data));
          if (o_.split_mb > 0 && static_cast<double>(writer_->bytes()) >= o_.split_mb * 1e6) rotate();
        }
        batch.clear();
        writer_->flush();
        confirm();
        if (g_rotate.exchange(false) ||
            (o_.split_s > 0 && std::chrono::steady_clock::now() - file_start_ >=
                                   std::chrono::duration<double>(o_.split_s)))
          rotate();
        std::lock_guard lock(mu_);
        written_bytes_ = written_total_ + writer_->bytes();
        if (last) written_total_ = written_bytes_;
      } catch (const std::exception& e) {
        if (writer_) confirm();  // what reached the file before the failure
        count_unwritten();
        std::lock_guard lock(mu_);
        if (error_.empty()) error_ = e.what();
        g_stop.store(true);
        batch.clear();
        writer_.reset();
      }
    }
    try {
      if (writer_) writer_->close();
    } catch (const std::exception& e) {
      confirm();
      count_unwritten();
      std::lock_guard lock(mu_);
      if (error_.empty()) error_ = e.what();
    }
  }

  // Writer thread. Events the writer has handed to the kernel leave `unconfirmed_` (in order).
  void confirm() {
    while (writer_->events_out() > confirmed_out_ && !unconfirmed_.empty()) {
      unconfirmed_.pop_front();
      ++confirmed_out_;
    }
  }
  // Writer thread, after a failed write: what is still unconfirmed never reached the file.
  void count_unwritten() {
    std::lock_guard lock(mu_);
    for (const auto& [channel, size] : unconfirmed_) {
      auto& c = counts_[*channel];
      --c.messages;
      c.bytes -= size;
      ++c.unwritten;
    }
    unconfirmed_.clear();
  }

  const RecordOptions& o_;
  Namer namer_;
  std::string first_;  // choose_first() -> open_first()
  eventlog::OpenMode first_mode_ = eventlog::OpenMode::create;
  std::optional<eventlog::Writer> writer_;  // writer thread only (after open_first)
  // Writer thread only: events given to writer_ and not yet known to be in the file (channel,
  // size), oldest first; confirmed_out_: writer_->events_out() already taken off it.
  std::deque<std::pair<const std::string*, std::size_t>> unconfirmed_;
  std::int64_t confirmed_out_ = 0;
  std::chrono::steady_clock::time_point file_start_;
  std::thread thread_;

  std::mutex mu_;
  std::condition_variable cv_;
  std::deque<Item> queue_;
  std::size_t queued_bytes_ = 0;
  std::size_t max_queued_ = static_cast<std::size_t>(o_.max_unwritten_mb * 1e6);
  std::vector<std::vector<std::byte>> pool_;
  std::set<std::string, std::less<>> names_;
  std::map<std::string, ChannelCount> counts_;
  std::vector<std::string> files_;
  std::uint64_t written_bytes_ = 0, written_total_ = 0;
  std::string error_;
  bool stopping_ = false;
};

std::string human_mb(std::uint64_t b) { return fmt("%.1f", static_cast<double>(b) / 1e6); }

}  // namespace

int run_record();

Verb add_record(CLI::App& app, const Globals& g) {
  g_rec.g = &g;
  auto* c = app.add_subcommand(
      "record",
      "record every channel (shm, bridges, UDP from other hosts, stock LCM programs) into an LCM "
      "log file, readable by lcm-logplayer and every LCM log reader");
  c->add_option("file", g_rec.file,
                "log file name (strftime patterns with --strftime); default lcmxlog-YYYY-MM-DD.NN "
                "(first unused NN), like lcm-logger");
  c->add_option("-c,--channel", g_rec.channel,
                "record channels whose whole name matches this regular expression")
      ->capture_default_str();
  c->add_option("-x,--exclude", g_rec.exclude, "leave out channels matching this expression (repeatable)")
      ->allow_extra_args(false);
  c->add_flag("-i,--increment", g_rec.increment, "add a suffix .NN to FILE so that no file is overwritten");
  c->add_flag("-f,--force", g_rec.force, "overwrite an existing FILE");
  c->add_flag("-a,--append", g_rec.append, "append to FILE (event numbers continue)");
  c->add_flag("-s,--strftime", g_rec.strftime_name, "format FILE with strftime (e.g. run-%H%M%S.lcmlog)");
  c->add_option("--rotate", g_rec.rotate,
                "keep NUM files: always write FILE.0, moving older ones to FILE.1 ... FILE.NUM-1 "
                "(the oldest is deleted) when a new file starts")
      ->check(CLI::Range(1, 10000));
  c->add_option("--split-mb", g_rec.split_mb,
                "start the next file (FILE.NN+1, or FILE.0 with --rotate) when this one reaches this many MB")
      ->check(non_negative_number());
  c->add_option("--split-duration", g_rec.split_s, "start the next file after this many seconds")
      ->check(non_negative_number());
  c->add_option("--max-duration", g_rec.max_duration_s, "stop after this many seconds (0: until SIGINT)")
      ->check(non_negative_number());
  c->add_option("--flush-interval", g_rec.flush_ms, "write to the file at least every MS milliseconds")
      ->check(CLI::Range(1, 60000))
      ->capture_default_str();
  c->add_option("-m,--max-unwritten-mb", g_rec.max_unwritten_mb,
                "received but unwritten messages kept in memory; beyond it new messages are "
                "dropped (counted per channel)")
      ->check(positive_number())
      ->capture_default_str();
  c->add_option("--queue-depth", g_rec.queue_depth,
                "per channel queue for UDP / in-process messages before the oldest is dropped")
      ->check(CLI::Range(1, 1 << 20))
      ->capture_default_str();
  c->add_option("--rt-priority", g_rec.rt_priority,
                "receive on SCHED_FIFO threads of this priority (1-99; needs CAP_SYS_NICE), so a "
                "busy machine does not delay reading shared memory (the writer thread stays normal)")
      ->check(CLI::Range(0, 99));
  c->add_flag("-q,--quiet", g_rec.quiet, "no status line and no summary (errors only)");
  c->add_flag("--json", g_rec.json, "print the summary as JSON on stdout");
  c->footer(
      "Signals: SIGINT/SIGTERM close the file cleanly; SIGHUP starts the next file (as "
      "lcm-logger: FILE.NN+1 with --increment, else FILE is reopened for appending, e.g. after "
      "logrotate moved it). A SIGKILL leaves a file readable up to its last complete event.");
  return {c, [] { return run_record(); }};
}

int run_record() {
  const auto& o = g_rec;
  spdlog::set_level(spdlog::level::warn);
  if (o.append && (o.force || o.split_mb > 0 || o.split_s > 0 || o.rotate > 0)) {
    std::cerr << "lcmx record: --append cannot be combined with --force, --rotate or --split-*\n";
    return 2;
  }
  if (o.rotate > 0 && o.increment) {
    std::cerr << "lcmx record: --rotate and --increment exclude each other\n";
    return 2;
  }
  std::optional<ChannelFilter> filter;
  try {
    filter.emplace(o.channel, o.exclude);
  } catch (const std::regex_error& e) {
    std::cerr << "lcmx record: bad channel expression: " << e.what() << "\n";
    return 2;
  }

  struct sigaction sa{};
  sa.sa_handler = on_stop_signal;
  sigemptyset(&sa.sa_mask);
  ::sigaction(SIGINT, &sa, nullptr);
  ::sigaction(SIGTERM, &sa, nullptr);
  sa.sa_handler = on_hup_signal;
  ::sigaction(SIGHUP, &sa, nullptr);

  Recorder rec(o);
  try {
    rec.choose_first();
  } catch (const std::exception& e) {
    std::cerr << "lcmx record: " << e.what() << "\n";
    return 1;
  }

  std::optional<Runtime> rt;
  std::optional<Node> node;
  ChannelSubscription sub;
  // --rt-priority: the runtime's and the node's threads inherit SCHED_FIFO from this thread
  // while they are created; this thread (status, signals) and the writer go back to normal.
  sched_param normal{};
  int normal_policy = SCHED_OTHER;
  ::pthread_getschedparam(::pthread_self(), &normal_policy, &normal);
  if (o.rt_priority > 0) {
    sched_param sp{};
    sp.sched_priority = o.rt_priority;
    if (const int e = ::pthread_setschedparam(::pthread_self(), SCHED_FIFO, &sp); e != 0) {
      std::cerr << "lcmx record: --rt-priority " << o.rt_priority << ": " << std::strerror(e) << "\n";
      return 1;
    }
  }
  // The runtime first: a bad configuration fails here, before any file exists.
  try {
    rt.emplace(Runtime::create(runtime_options(*o.g)));
    node.emplace(rt->create_node("lcmx_record"));
  } catch (const std::exception& e) {
    std::cerr << "lcmx record: " << e.what() << "\n";
    return 1;
  }
  if (o.rt_priority > 0) ::pthread_setschedparam(::pthread_self(), normal_policy, &normal);
  try {
    rec.open_first();
  } catch (const std::exception& e) {
    std::cerr << "lcmx record: " << e.what() << "\n";
    return 1;
  }
  rec.start_writer();
  try {
    SubscriberOptions so;
    so.queue_depth = o.queue_depth;
    so.policy = QueuePolicy::drop_oldest;
    auto f = std::make_shared<ChannelFilter>(*filter);
    sub = node->subscribe_channels([f](const std::string& ch) { return (*f)(ch); },
                                   [&rec](const RawMessage& m) { rec.on_message(m); }, so);
  } catch (const std::exception& e) {
    std::cerr << "lcmx record: " << e.what() << "\n";
    rec.stop_writer();
    return 1;
  }
  if (!o.quiet) std::cerr << "lcmx record: recording to " << rec.files().front() << std::endl;

  using Clock = std::chrono::steady_clock;
  const auto start = Clock::now();
  const bool tty = !o.quiet && ::isatty(STDERR_FILENO);
  std::uint64_t last_bytes = 0;
  auto last_t = start;
  double rate = 0;
  auto drops_of = [&](const std::map<std::string, SubscriberStats>& st, const std::string& ch,
                      const ChannelCount& c) {
    auto it = st.find(ch);
    return c.recorder_drops + c.unwritten + (it == st.end() ? 0 : it->second.drops);
  };
  while (!g_stop.load()) {
    std::this_thread::sleep_for(std::chrono::milliseconds(tty ? 250 : 50));
    const auto now = Clock::now();
    if (o.max_duration_s > 0 && now - start >= std::chrono::duration<double>(o.max_duration_s)) break;
    if (rec.failed()) break;
    if (tty && now - last_t >= std::chrono::milliseconds(500)) {
      const auto s = rec.snapshot();
      std::map<std::string, SubscriberStats> st;
      for (auto& [ch, x] : sub.stats()) st[ch] = std::move(x);
      std::uint64_t msgs = 0, bytes = 0;
      std::vector<std::pair<std::uint64_t, std::string>> dropping;
      for (const auto& [ch, c] : s.counts) {
        msgs += c.messages;
        bytes += c.bytes;
        if (const auto d = drops_of(st, ch, c)) dropping.push_back({d, ch});
      }
      rate = static_cast<double>(bytes - last_bytes) / 1e6 /
             std::chrono::duration<double>(now - last_t).count();
      last_bytes = bytes;
      last_t = now;
      std::sort(dropping.rbegin(), dropping.rend());
      std::ostringstream line;
      line << "\r\x1b[K" << fmt("%.0f s", std::chrono::duration<double>(now - start).count()) << "  "
           << msgs << " msgs  " << human_mb(bytes) << " MB  " << fmt("%.2f", rate) << " MB/s  "
           << s.counts.size() << " channels  -> " << s.file;
      if (!dropping.empty()) {
        line << "  drops:";
        for (std::size_t i = 0; i < std::min<std::size_t>(3, dropping.size()); ++i)
          line << " " << printable(dropping[i].second) << "=" << dropping[i].first;
        if (dropping.size() > 3) line << " (+" << dropping.size() - 3 << " channels)";
      }
      std::cerr << line.str() << std::flush;
    }
  }
  // Stop receiving first (no callback runs after this), then drain the queue to the file.
  std::map<std::string, SubscriberStats> st;
  for (auto& [ch, x] : sub.stats()) st[ch] = std::move(x);
  sub.reset();
  node.reset();
  rt.reset();
  rec.stop_writer();
  if (tty) std::cerr << "\r\x1b[K";

  const auto s = rec.snapshot();
  const double secs = std::chrono::duration<double>(Clock::now() - start).count();
  std::uint64_t msgs = 0, bytes = 0, lost = 0;
  for (const auto& [ch, c] : s.counts) {
    msgs += c.messages;
    bytes += c.bytes;
    lost += drops_of(st, ch, c);
  }
  if (o.json) {
    std::ostringstream j;
    j << "{\"files\":[";
    const auto files = rec.files();
    for (std::size_t i = 0; i < files.size(); ++i) j << (i ? "," : "") << json_str(files[i]);
    j << "],\"seconds\":" << fmt("%.3f", secs) << ",\"messages\":" << msgs << ",\"bytes\":" << bytes
      << ",\"lost\":" << lost << ",\"channels\":[";
    bool first = true;
    for (const auto& [ch, c] : s.counts) {
      auto it = st.find(ch);
      const std::uint64_t td = it == st.end() ? 0 : it->second.drops;
      j << (first ? "" : ",") << "{\"channel\":" << json_str(ch) << ",\"messages\":" << c.messages
        << ",\"bytes\":" << c.bytes << ",\"transport_drops\":" << td
        << ",\"recorder_drops\":" << c.recorder_drops << ",\"unwritten\":" << c.unwritten
        << ",\"lost\":" << td + c.recorder_drops + c.unwritten << "}";
      first = false;
    }
    j << "]";
    if (!s.error.empty()) j << ",\"error\":" << json_str(s.error);
    j << "}";
    std::cout << j.str() << std::endl;
  } else if (!o.quiet) {
    std::cout << "lcmx record: " << msgs << " messages, " << human_mb(bytes) << " MB in "
              << fmt("%.1f", secs) << " s, " << lost << " lost; files:";
    for (const auto& f : rec.files()) std::cout << " " << f;
    std::cout << "\n";
    if (!s.counts.empty()) {
      char line[256];
      std::snprintf(line, sizeof line, "  %-40s %10s %12s %10s\n", "channel", "messages", "MB", "lost");
      std::cout << line;
      for (const auto& [ch, c] : s.counts) {
        std::snprintf(line, sizeof line, "  %-40s %10llu %12.3f %10llu\n", printable(ch).c_str(),
                      static_cast<unsigned long long>(c.messages), static_cast<double>(c.bytes) / 1e6,
                      static_cast<unsigned long long>(drops_of(st, ch, c)));
        std::cout << line;
      }
    }
  }
  if (!s.error.empty()) {
    std::cerr << "lcmx record: " << s.error << "\n";
    return 1;
  }
  return 0;
}

}  // namespace lcmx::cli
