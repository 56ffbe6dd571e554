#include "mcap_writer.hpp"

#include <zlib.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <stdexcept>
#include <utility>

namespace lcmx::cli {
namespace {

constexpr unsigned char kMagic[8] = {0x89, 'M', 'C', 'A', 'P', '0', '\r', '\n'};

enum Op : std::uint8_t {
  kHeader = 0x01,
  kFooter = 0x02,
  kSchema = 0x03,
  kChannel = 0x04,
  kMessage = 0x05,
  kStatistics = 0x0B,
  kSummaryOffset = 0x0E,
  kDataEnd = 0x0F,
};

// MCAP serialisation: little-endian integers, strings and byte blocks with a uint32 length.
void u8(std::string& o, std::uint8_t v) { o.push_back(static_cast<char>(v)); }
template <class T>
void le(std::string& o, T v) {
  for (std::size_t i = 0; i < sizeof(T); ++i) o.push_back(static_cast<char>((static_cast<std::uint64_t>(v) >> (8 * i)) & 0xff));
}
void str(std::string& o, std::string_view s) {
  if (s.size() > UINT32_MAX) throw std::length_error("MCAP string longer than 4 GiB");
  le<std::uint32_t>(o, static_cast<std::uint32_t>(s.size()));
  o.append(s);
}

std::uint32_t crc_update(std::uint32_t crc, const void* p, std::size_t n) {
  const auto* b = static_cast<const Bytef*>(p);
  while (n > 0) {  // zlib takes uInt lengths
    const auto k = static_cast<uInt>(std::min<std::size_t>(n, 1u << 30));
    crc = static_cast<std::uint32_t>(::crc32(crc, b, k));
    b += k;
    n -= k;
  }
  return crc;
}

}  // namespace

McapWriter McapWriter::open(const std::string& path) {
  std::FILE* f = std::fopen(path.c_str(), "wb");
  if (f == nullptr) throw std::runtime_error("cannot create " + path + ": " + std::strerror(errno));
  McapWriter w(f, path);
  std::setvbuf(f, nullptr, _IOFBF, 1 << 20);
  w.raw(kMagic, sizeof kMagic);
  std::string h;
  str(h, "");  // profile: none of the well-known ones
  str(h, "lcmx log export");
  w.record(kHeader, h);
  return w;
}

McapWriter::McapWriter(std::FILE* f, std::string path) : f_(f), path_(std::move(path)) {}

McapWriter::McapWriter(McapWriter&& o) noexcept
    : f_(std::exchange(o.f_, nullptr)), path_(std::move(o.path_)), offset_(o.offset_), crc_(o.crc_),
      schemas_(std::move(o.schemas_)), channels_(std::move(o.channels_)), channel_counts_(std::move(o.channel_counts_)),
      message_count_(o.message_count_), first_ns_(o.first_ns_), last_ns_(o.last_ns_) {}

McapWriter::~McapWriter() {
  if (f_ != nullptr) std::fclose(f_);
}

void McapWriter::raw(const void* p, std::size_t n) {
  if (n > 0 && std::fwrite(p, 1, n, f_) != n) throw std::runtime_error("cannot write " + path_ + ": " + std::strerror(errno));
  crc_ = crc_update(crc_, p, n);
  offset_ += n;
}

void McapWriter::record(std::uint8_t opcode, const std::string& content) {
  std::string head;
  u8(head, opcode);
  le<std::uint64_t>(head, content.size());
  raw(head.data(), head.size());
  raw(content.data(), content.size());
}

std::uint16_t McapWriter::add_schema(std::string_view name, std::string_view encoding, std::string_view data) {
  if (schemas_.size() >= 65535) throw std::length_error("more than 65535 schemas (MCAP's limit)");
  const auto id = static_cast<std::uint16_t>(schemas_.size() + 1);
  std::string c;
  le<std::uint16_t>(c, id);
  str(c, name);
  str(c, encoding);
  str(c, data);
  record(kSchema, c);
  schemas_.push_back(std::move(c));
  return id;
}

std::uint16_t McapWriter::add_channel(std::uint16_t schema_id, std::string_view topic, std::string_view message_encoding,
                                      const std::map<std::string, std::string>& metadata) {
  if (channels_.size() >= 65536) throw std::length_error("more than 65536 channels (MCAP's limit)");
  const auto id = static_cast<std::uint16_t>(channels_.size());
  std::string c;
  le<std::uint16_t>(c, id);
  le<std::uint16_t>(c, schema_id);
  str(c, topic);
  str(c, message_encoding);
  std::string map;
  for (const auto& [k, v] : metadata) {
    str(map, k);
    str(map, v);
  }
  str(c, map);
  record(kChannel, c);
  channels_.push_back(std::move(c));
  channel_counts_.push_back(0);
  return id;
}

void McapWriter::add_message(std::uint16_t channel_id, std::uint32_t sequence, std::uint64_t log_time_ns,
                             std::uint64_t publish_time_ns, std::string_view data) {
  std::string head;
  u8(head, kMessage);
  le<std::uint64_t>(head, 2 + 4 + 8 + 8 + data.size());
  le<std::uint16_t>(head, channel_id);
  le<std::uint32_t>(head, sequence);
  le<std::uint64_t>(head, log_time_ns);
  le<std::uint64_t>(head, publish_time_ns);
  raw(head.data(), head.size());
  raw(data.data(), data.size());
  if (message_count_ == 0) first_ns_ = last_ns_ = log_time_ns;
  first_ns_ = std::min(first_ns_, log_time_ns);
  last_ns_ = std::max(last_ns_, log_time_ns);
  ++message_count_;
  ++channel_counts_.at(channel_id);
}

void McapWriter::close() {
  if (f_ == nullptr) return;
  // Data End: CRC32 of every byte from the start of the file up to this record.
  std::string de;
  le<std::uint32_t>(de, crc_);
  record(kDataEnd, de);

  // Summary: groups by opcode (schemas, channels, statistics), then one Summary Offset each.
  const std::uint64_t summary_start = offset_;
  crc_ = 0;  // the footer's CRC covers the summary sections and the footer's first fields
  struct Group {
    std::uint8_t op;
    std::uint64_t start, length;
  };
  std::vector<Group> groups;
  auto group = [&](std::uint8_t op, const std::vector<std::string>& contents) {
    if (contents.empty()) return;
    const std::uint64_t start = offset_;
    for (const auto& c : contents) record(op, c);
    groups.push_back({op, start, offset_ - start});
  };
  group(kSchema, schemas_);
  group(kChannel, channels_);
  std::string st;
  le<std::uint64_t>(st, message_count_);
  le<std::uint16_t>(st, static_cast<std::uint16_t>(schemas_.size()));
  le<std::uint32_t>(st, static_cast<std::uint32_t>(channels_.size()));
  le<std::uint32_t>(st, 0);  // attachments
  le<std::uint32_t>(st, 0);  // metadata
  le<std::uint32_t>(st, 0);  // chunks
  le<std::uint64_t>(st, message_count_ ? first_ns_ : 0);
  le<std::uint64_t>(st, message_count_ ? last_ns_ : 0);
  std::string counts;
  for (std::size_t i = 0; i < channel_counts_.size(); ++i) {
    le<std::uint16_t>(counts, static_cast<std::uint16_t>(i));
    le<std::uint64_t>(counts, channel_counts_[i]);
  }
  str(st, counts);
  group(kStatistics, {st});
  const std::uint64_t summary_offset_start = offset_;
  for (const auto& g : groups) {
    std::string so;
    u8(so, g.op);
    le<std::uint64_t>(so, g.start);
    le<std::uint64_t>(so, g.length);
    record(kSummaryOffset, so);
  }
  // Footer: the CRC covers everything from summary_start through summary_offset_start.
  std::string head;
  u8(head, kFooter);
  le<std::uint64_t>(head, 8 + 8 + 4);
  le<std::uint64_t>(head, summary_start);
  le<std::uint64_t>(head, summary_offset_start);
  raw(head.data(), head.size());
  std::string crc;
  le<std::uint32_t>(crc, crc_);
  raw(crc.data(), crc.size());
  raw(kMagic, sizeof kMagic);
  std::FILE* f = std::exchange(f_, nullptr);
  if (std::fflush(f) != 0 || std::ferror(f)) {
    const int err = errno;
    std::fclose(f);
    throw std::runtime_error("cannot write " + path_ + ": " + std::strerror(err));
  }
  if (std::fclose(f) != 0) throw std::runtime_error("cannot close " + path_ + ": " + std::strerror(errno));
}

}  // namespace lcmx::cli
