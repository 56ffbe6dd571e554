// lcmx::eventlog — LCM's event-log file format: a writer and a damage-tolerant reader.
//
// Format (big-endian), per event: sync word 0xEDA1DA01, int64 event number, int64 timestamp
// (µs since the Unix epoch), int32 channel length, int32 data length, the channel bytes (no
// NUL), the data bytes. Files written here are byte-identical to liblcm's lcm_eventlog for
// the same events (event numbers 0, 1, 2 … per file).
//
// Errors: real I/O faults (cannot open, write fails) throw eventlog::Error. Damage in a file
// being read is not an error: the Reader skips it, resynchronising on the sync word, and
// reports it (damage()).
// Threads: a Reader or Writer is used by one thread at a time. Move-only RAII (closes the fd).
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

namespace lcmx::eventlog {

inline constexpr std::uint32_t kSyncWord = 0xEDA1DA01u;
inline constexpr std::size_t kHeaderSize = 28;
// Longest channel name the Reader accepts (LCM's UDP limit is 63; logs may hold longer ones).
inline constexpr std::size_t kMaxChannelLength = 1024;

class Error : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// The 28-byte header of one event, big-endian, into `out`.
void encode_header(std::byte* out, std::int64_t number, std::int64_t timestamp_us,
                   std::uint32_t channel_length, std::uint32_t data_length);

struct Event {
  std::int64_t number = 0;
  std::int64_t timestamp_us = 0;
  std::string channel;
  std::vector<std::byte> data;  // the data, or only its first ReaderOptions::data_prefix bytes
  std::size_t size = 0;         // the data's full length
  std::uint64_t offset = 0;     // of its sync word in the file
};

// A byte range of the file that holds no acceptable event.
struct Damage {
  enum class Kind {
    corrupt,    // bytes skipped before the next acceptable event
    truncated,  // the file ends inside an event (or with bytes that start none)
  };
  Kind kind = Kind::corrupt;
  std::uint64_t offset = 0;
  std::uint64_t length = 0;
};
const char* to_string(Damage::Kind k);

struct ReaderOptions {
  // Read only header, channel and the first `data_prefix` data bytes of each event (the rest
  // is skipped: fast scans, e.g. for the fingerprint). SIZE_MAX: whole events.
  std::size_t data_prefix = SIZE_MAX;
};

class Reader {
 public:
  // Opens a regular file for reading. Throws Error if it cannot be opened or is not a regular
  // file (the reader seeks: pipes are not supported).
  static Reader open(const std::string& path, ReaderOptions options = {});

  Reader(Reader&& o) noexcept;
  Reader& operator=(Reader&& o) noexcept;
  Reader(const Reader&) = delete;
  Reader& operator=(const Reader&) = delete;
  ~Reader();

  // The next acceptable event into `e` (its buffers are reused): true, or false at the end of
  // the file. Damage met on the way is appended to damage(). Never throws on damaged content;
  // throws Error on an I/O error.
  bool next(Event& e);
  // Moves to byte `offset` (e.g. an Event::offset seen before); the next event is searched
  // from there.
  void seek(std::uint64_t offset);

  // Damage found so far, in file order (at most 1000 entries kept; damage_count() counts all).
  const std::vector<Damage>& damage() const { return damage_; }
  std::uint64_t damage_count() const { return damage_count_; }
  std::uint64_t damaged_bytes() const { return damaged_bytes_; }
  std::uint64_t position() const { return pos_; }
  // The file's size when last looked at (it is re-read at the end, for files still growing).
  std::uint64_t size() const { return size_; }

 private:
  Reader(int fd, ReaderOptions o);
  void refresh_size();
  std::size_t read_at(std::uint64_t off, void* buf, std::size_t n);
  bool header_at(std::uint64_t off, std::int64_t& number, std::int64_t& ts,
                 std::uint32_t& chlen, std::uint32_t& dlen, bool& truncated);
  std::optional<std::uint64_t> find_sync(std::uint64_t from);
  void add_damage(Damage::Kind k, std::uint64_t off, std::uint64_t len);

  int fd_ = -1;
  ReaderOptions options_;
  std::uint64_t pos_ = 0;
  std::uint64_t size_ = 0;
  // Read-ahead window [win_off_, win_off_ + win_.size()).
  std::vector<std::byte> win_;
  std::uint64_t win_off_ = 0;
  std::size_t win_len_ = 0;
  std::vector<Damage> damage_;
  std::uint64_t damage_count_ = 0;
  std::uint64_t damaged_bytes_ = 0;
};

enum class OpenMode {
  create,     // a new file; Error if it exists
  overwrite,  // create or truncate
  append,     // add to the end (event numbers continue after the file's last event; a torn
              // last event is cut off first)
};

class Writer {
 public:
  // Throws Error if the file cannot be opened as asked.
  static Writer open(const std::string& path, OpenMode mode);

  Writer(Writer&& o) noexcept;
  Writer& operator=(Writer&& o) noexcept;
  Writer(const Writer&) = delete;
  Writer& operator=(const Writer&) = delete;
  // Flushes and closes; errors are swallowed here (call close() to see them).
  ~Writer();

  // Appends one event with the next event number. Small events are buffered (up to 1 MiB,
  // then written); large data is written at once without a copy. Throws Error on a write
  // error (e.g. disk full) or a channel longer than kMaxChannelLength / empty.
  void write(std::int64_t timestamp_us, std::string_view channel, std::span<const std::byte> data);
  // Writes buffered events to the file (the page cache; no fsync).
  void flush();
  // Flushes and closes. Throws Error on failure. Idempotent.
  void close();

  const std::string& path() const { return path_; }
  std::uint64_t bytes() const { return bytes_; }    // file size including buffered events
  std::int64_t events() const { return next_number_ - first_number_; }  // written by this Writer
  // Of events(): those wholly handed to the kernel (not in the buffer, not cut off by a failed
  // write). After a write error, the events written after the first events_out() are lost.
  std::int64_t events_out() const { return events_out_; }

 private:
  Writer(int fd, std::string path, std::uint64_t size, std::int64_t next_number);
  // Writes all n bytes or throws Error; *done (if given) grows by what was written.
  void write_all(const void* p, std::size_t n, std::size_t* done = nullptr);

  int fd_ = -1;
  std::string path_;
  std::vector<std::byte> buf_;
  std::uint64_t bytes_ = 0;
  std::int64_t next_number_ = 0;
  std::int64_t first_number_ = 0;
  std::vector<std::size_t> buf_ends_;  // where each event in buf_ ends
  std::int64_t events_out_ = 0;
};

}  // namespace lcmx::eventlog
