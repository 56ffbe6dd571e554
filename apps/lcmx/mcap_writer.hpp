// A minimal MCAP writer (https://mcap.dev/spec, major version 0), written from the spec for
// `lcmx log export --format mcap`. No Debian package provides MCAP.
//
// What it writes: magic, Header (profile "", library "lcmx"), then in the data section the
// Schema and Channel records (each before the first Message that uses it) and one Message
// record per message, unchunked and uncompressed; then Data End with the CRC32 of every byte
// before it (from the first byte of the file, magic included); a summary section with a copy
// of every Schema and Channel and one Statistics record (counts per channel, first/last log
// time); a Summary Offset record per group; the Footer with the CRC32 of the summary and
// summary offset sections; the closing magic. No chunks, hence no message/chunk indexes:
// readers read it front to back (Foxglove and the mcap CLI do).
//
// Errors: I/O faults throw std::runtime_error naming the file and errno. More than 65535
// schemas or channels (MCAP ids are uint16) is a std::length_error.
// Thread: one thread at a time. Move-only; the destructor closes without the summary if
// close() was not called (the file is then a valid MCAP data section without footer:
// readers report it as truncated).
#pragma once

#include <cstdint>
#include <cstdio>
#include <map>
#include <string>
#include <string_view>
#include <vector>

namespace lcmx::cli {

class McapWriter {
 public:
  // Creates (or truncates) `path` and writes the magic and the Header.
  static McapWriter open(const std::string& path);

  McapWriter(McapWriter&& o) noexcept;
  McapWriter& operator=(McapWriter&&) = delete;
  McapWriter(const McapWriter&) = delete;
  McapWriter& operator=(const McapWriter&) = delete;
  ~McapWriter();

  // Writes a Schema record; returns its id (1, 2, ...).
  std::uint16_t add_schema(std::string_view name, std::string_view encoding, std::string_view data);
  // Writes a Channel record; returns its id (0, 1, ...).
  std::uint16_t add_channel(std::uint16_t schema_id, std::string_view topic, std::string_view message_encoding,
                            const std::map<std::string, std::string>& metadata);
  // Writes a Message record on a channel returned by add_channel().
  void add_message(std::uint16_t channel_id, std::uint32_t sequence, std::uint64_t log_time_ns,
                   std::uint64_t publish_time_ns, std::string_view data);
  // Writes Data End, the summary, the footer and the closing magic, and closes the file.
  void close();

  std::uint64_t bytes() const { return offset_; }
  std::uint64_t messages() const { return message_count_; }

 private:
  McapWriter(std::FILE* f, std::string path);
  // A record: opcode, uint64 length, content. Updates the data CRC while in the data section.
  void record(std::uint8_t opcode, const std::string& content);
  void raw(const void* p, std::size_t n);

  std::FILE* f_ = nullptr;
  std::string path_;
  std::uint64_t offset_ = 0;
  std::uint32_t crc_ = 0;  // running CRC32 of everything written so far (see close())
  std::vector<std::string> schemas_;   // contents of the Schema records, id-1 indexed
  std::vector<std::string> channels_;  // contents of the Channel records, id indexed
  std::vector<std::uint64_t> channel_counts_;
  std::uint64_t message_count_ = 0;
  std::uint64_t first_ns_ = 0, last_ns_ = 0;
};

}  // namespace lcmx::cli
