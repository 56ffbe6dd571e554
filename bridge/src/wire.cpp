#include "lcmx/bridge/detail/wire.hpp"

#include <algorithm>
#include <charconv>
#include <cstdio>

namespace lcmx::bridge::wire {
namespace {

constexpr std::size_t kMaxLines = 200000;

bool valid_word(std::string_view s, std::size_t max) {
  if (s.empty() || s.size() > max) return false;
  for (unsigned char c : s)
    if (c <= ' ' || c == 0x7f) return false;
  return true;
}

template <class T>
bool parse_num(std::string_view s, T& out, int base = 10) {
  if (s.empty()) return false;
  auto [p, ec] = std::from_chars(s.data(), s.data() + s.size(), out, base);
  return ec == std::errc() && p == s.data() + s.size();
}

}  // namespace

bool valid_topic(std::string_view t) {
  return !t.empty() && t.size() <= kMaxTopic && t.find('\0') == std::string_view::npos;
}

namespace {
bool needs_escape(unsigned char c) { return c <= ' ' || c == 0x7f || c == '%'; }
constexpr char kHex[] = "0123456789ABCDEF";
int hex_digit(char c) {  // upper case only: one spelling per byte
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'A' && c <= 'F') return c - 'A' + 10;
  return -1;
}
}  // namespace

std::string encode_topic(std::string_view t) {
  std::string o;
  o.reserve(t.size());
  for (unsigned char c : t) {
    if (needs_escape(c)) {
      o += '%';
      o += kHex[c >> 4];
      o += kHex[c & 0xf];
    } else {
      o += static_cast<char>(c);
    }
  }
  return o;
}

std::optional<std::string> decode_topic(std::string_view w) {
  if (w.empty() || w.size() > 3 * kMaxTopic) return std::nullopt;
  std::string t;
  for (std::size_t i = 0; i < w.size(); ++i) {
    const auto c = static_cast<unsigned char>(w[i]);
    if (c == '%') {
      if (i + 2 >= w.size()) return std::nullopt;
      const int hi = hex_digit(w[i + 1]), lo = hex_digit(w[i + 2]);
      if (hi < 0 || lo < 0) return std::nullopt;
      const auto b = static_cast<unsigned char>(hi << 4 | lo);
      if (!needs_escape(b)) return std::nullopt;  // not the canonical spelling
      t += static_cast<char>(b);
      i += 2;
    } else if (needs_escape(c)) {
      return std::nullopt;  // a byte that must be escaped, bare
    } else {
      t += static_cast<char>(c);
    }
  }
  if (!valid_topic(t)) return std::nullopt;
  return t;
}
bool valid_type_name(std::string_view name) { return valid_word(name, Control::kMaxTypeName); }

std::string encode(const Control& c) {
  std::string s = c.kind == Control::Kind::ping ? "LCMXB1 PING\n" : "LCMXB1 PONG\n";
  char hex[32];
  std::snprintf(hex, sizeof hex, "%016llx", static_cast<unsigned long long>(c.instance));
  s += "from " + c.from + "\ninstance " + hex + "\nlink " + c.link + "\nt " + std::to_string(c.t_ns) + "\n";
  if (c.kind == Control::Kind::ping) {
    if (c.active) s += "active\n";
    if (c.has_demand) {
      s += "control " + std::to_string(c.control_port) + "\n";
      for (const auto& [name, port] : c.channels) s += "channel " + name + " " + std::to_string(port) + "\n";
      s += "demand\n";
      for (const auto& t : c.want) {
        s += "want " + encode_topic(t);
        if (auto a = c.want_age_ms.find(t); a != c.want_age_ms.end() && a->second > 0)
          s += " " + std::to_string(std::min(a->second, Control::kMaxWantAgeMs));
        s += "\n";
      }
      for (const auto& t : c.offer) s += "offer " + encode_topic(t) + "\n";
      for (const auto& [t, n] : c.keep) s += "keep " + encode_topic(t) + " " + std::to_string(n) + "\n";
      for (const auto& t : c.have) s += "have " + encode_topic(t) + "\n";
      for (const auto& [t, ty] : c.types) {
        std::snprintf(hex, sizeof hex, "%016llx", static_cast<unsigned long long>(ty.fingerprint));
        s += "type " + encode_topic(t) + " " + hex + " " + ty.name + "\n";
      }
    }
  }
  return s;
}

std::optional<Control> decode(std::string_view f) {
  if (f.size() > kMaxControlFrame) return std::nullopt;
  Control c;
  std::size_t pos = 0, lines = 0;
  bool first = true, have_from = false, have_instance = false, have_link = false, have_t = false;
  bool have_control = false;
  while (pos < f.size()) {
    if (++lines > kMaxLines) return std::nullopt;
    const auto nl = f.find('\n', pos);
    const std::string_view line = f.substr(pos, nl == std::string_view::npos ? std::string_view::npos : nl - pos);
    pos = nl == std::string_view::npos ? f.size() : nl + 1;
    if (first) {
      if (line == "LCMXB1 PING") c.kind = Control::Kind::ping;
      else if (line == "LCMXB1 PONG") c.kind = Control::Kind::pong;
      else return std::nullopt;
      first = false;
      continue;
    }
    const auto sp = line.find(' ');
    const std::string_view key = line.substr(0, sp);
    const std::string_view val = sp == std::string_view::npos ? std::string_view{} : line.substr(sp + 1);
    if (key == "from") {
      if (!valid_word(val, 32)) return std::nullopt;
      c.from = val, have_from = true;
    } else if (key == "instance") {
      if (val.size() != 16 || !parse_num(val, c.instance, 16)) return std::nullopt;
      have_instance = true;
    } else if (key == "link") {
      if (!valid_word(val, 32)) return std::nullopt;
      c.link = val, have_link = true;
    } else if (key == "t") {
      if (!parse_num(val, c.t_ns)) return std::nullopt;
      have_t = true;
    } else if (c.kind != Control::Kind::ping) {
      return std::nullopt;
    } else if (key == "control") {
      if (!parse_num(val, c.control_port) || c.control_port < 1 || c.control_port > 65535) return std::nullopt;
      have_control = true;
    } else if (key == "channel") {
      const auto sp2 = val.find(' ');
      if (sp2 == std::string_view::npos) return std::nullopt;
      int port = 0;
      if (!valid_word(val.substr(0, sp2), 32) || !parse_num(val.substr(sp2 + 1), port) || port < 1 || port > 65535)
        return std::nullopt;
      if (c.channels.size() >= 256) return std::nullopt;
      c.channels.emplace_back(std::string(val.substr(0, sp2)), port);
    } else if (key == "active" && val.empty()) {
      c.active = true;
    } else if (key == "demand" && val.empty()) {
      c.has_demand = true;
    } else if ((key == "want" || key == "offer") && c.has_demand) {
      auto& set = key == "want" ? c.want : c.offer;
      if (set.size() >= kMaxDemand) return std::nullopt;
      // "want <topic> <age ms>": the age is optional (0), and only on "want".
      const auto sp2 = key == "want" ? val.find(' ') : std::string_view::npos;
      std::uint32_t age = 0;
      if (sp2 != std::string_view::npos &&
          (!parse_num(val.substr(sp2 + 1), age) || age == 0 || age > Control::kMaxWantAgeMs))
        return std::nullopt;
      auto t = decode_topic(val.substr(0, sp2));
      if (!t) return std::nullopt;
      if (age > 0) c.want_age_ms[*t] = age;
      set.insert(std::move(*t));
    } else if (key == "keep" && c.has_demand) {
      const auto sp2 = val.find(' ');
      std::uint32_t n = 0;
      if (sp2 == std::string_view::npos || !parse_num(val.substr(sp2 + 1), n) || n > Control::kMaxKeep ||
          c.keep.size() >= kMaxCatalogue)
        return std::nullopt;
      auto t = decode_topic(val.substr(0, sp2));
      if (!t) return std::nullopt;
      c.keep[std::move(*t)] = n;
    } else if (key == "type" && c.has_demand) {
      // "<topic> <16 hex> <name>"
      const auto sp2 = val.find(' ');
      if (sp2 == std::string_view::npos) return std::nullopt;
      const auto rest = val.substr(sp2 + 1);
      const auto sp3 = rest.find(' ');
      std::uint64_t fp = 0;
      if (sp3 != 16 || !parse_num(rest.substr(0, 16), fp, 16) || !valid_type_name(rest.substr(17)) ||
          c.types.size() >= kMaxCatalogue)
        return std::nullopt;
      auto t = decode_topic(val.substr(0, sp2));
      if (!t) return std::nullopt;
      c.types[std::move(*t)] = {static_cast<std::int64_t>(fp), std::string(rest.substr(17))};
    } else if (key == "have" && c.has_demand) {
      if (c.have.size() >= kMaxCatalogue) return std::nullopt;
      auto t = decode_topic(val);
      if (!t) return std::nullopt;
      c.have.insert(std::move(*t));
    } else {
      return std::nullopt;
    }
  }
  if (first || !have_from || !have_instance || !have_link || !have_t) return std::nullopt;
  // The demand state is whole or absent: "control" (and "channel") belong to it. A "demand"
  // without "control" would read as control port 0 (a false hello mismatch), and either without
  // "demand" would be ignored; no encoder writes them.
  if (c.has_demand != have_control) return std::nullopt;
  if (!c.has_demand && !c.channels.empty()) return std::nullopt;
  return c;
}

void encode_header(const DataHeader& h, unsigned char out[kDataHeader]) {
  for (int i = 0; i < 8; ++i) {
    out[i] = static_cast<unsigned char>(h.instance >> (8 * i));
    out[8 + i] = static_cast<unsigned char>(h.seq >> (8 * i));
    out[16 + i] = static_cast<unsigned char>(h.keep >> (8 * i));
  }
}

DataHeader decode_header(const unsigned char in[kDataHeader]) {
  DataHeader h;
  for (int i = 0; i < 8; ++i) {
    h.instance |= std::uint64_t{in[i]} << (8 * i);
    h.seq |= std::uint64_t{in[8 + i]} << (8 * i);
    h.keep |= std::uint64_t{in[16 + i]} << (8 * i);
  }
  return h;
}

}  // namespace lcmx::bridge::wire
