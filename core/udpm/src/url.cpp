#include <arpa/inet.h>
#include <net/if.h>

#include <charconv>
#include <limits>
#include <string>

#include "lcmx/udpm/config.hpp"
#include "lcmx/udpm/error.hpp"

namespace lcmx::udpm {
namespace {

constexpr std::string_view kScheme = "udpm://";

[[noreturn]] void bad(std::string_view url, const std::string& why) {
  throw Error(Error::Code::invalid_config,
              "udpm url '" + std::string(url) + "': " + why);
}

template <typename Int>
bool parse_int(std::string_view s, Int& out) {
  if (s.empty()) return false;
  const auto* end = s.data() + s.size();
  auto [p, ec] = std::from_chars(s.data(), end, out);
  return ec == std::errc{} && p == end;
}

}  // namespace

GroupConfig parse_url(std::string_view url) {
  GroupConfig cfg;
  if (url.substr(0, kScheme.size()) != kScheme) bad(url, "expected it to start with 'udpm://'");
  std::string_view rest = url.substr(kScheme.size());
  std::string_view query;
  if (const auto q = rest.find('?'); q != std::string_view::npos) {
    query = rest.substr(q + 1);
    rest = rest.substr(0, q);
  }

  // network part: [ADDRESS][:PORT]
  std::string_view address = rest;
  if (const auto colon = rest.rfind(':'); colon != std::string_view::npos) {
    address = rest.substr(0, colon);
    const std::string_view port = rest.substr(colon + 1);
    unsigned long value = 0;
    if (!parse_int(port, value) || value == 0 || value > 65535)
      bad(url, "bad port '" + std::string(port) + "' (expected 1..65535)");
    cfg.port = static_cast<std::uint16_t>(value);
  }
  if (!address.empty()) {
    in_addr a{};
    const std::string addr(address);
    if (inet_pton(AF_INET, addr.c_str(), &a) != 1)
      bad(url, "bad address '" + addr + "' (expected a dotted IPv4 address)");
    if (!IN_MULTICAST(ntohl(a.s_addr)))
      bad(url, "address '" + addr + "' is not IPv4 multicast (224.0.0.0/4)");
    cfg.address = addr;
  }

  bool seen_ttl = false, seen_iface = false, seen_buf = false, seen_loop = false;
  auto once = [&](bool& seen, std::string_view key) {
    if (seen) bad(url, "option '" + std::string(key) + "' given twice");
    seen = true;
  };
  while (!query.empty()) {
    const auto amp = query.find('&');
    const std::string_view item = query.substr(0, amp);
    query = amp == std::string_view::npos ? std::string_view{} : query.substr(amp + 1);
    if (item.empty()) continue;
    const auto eq = item.find('=');
    if (eq == std::string_view::npos) bad(url, "option '" + std::string(item) + "' has no '='");
    const std::string_view key = item.substr(0, eq);
    const std::string_view value = item.substr(eq + 1);
    const std::string shown = "'" + std::string(key) + "=" + std::string(value) + "'";
    if (key == "ttl") {
      once(seen_ttl, key);
      int ttl = -1;
      if (!parse_int(value, ttl) || ttl < 0 || ttl > 255) bad(url, "bad " + shown + " (expected 0..255)");
      cfg.ttl = ttl;
    } else if (key == "iface") {
      once(seen_iface, key);
      if (value.empty() || value.size() >= IFNAMSIZ)
        bad(url, "bad " + shown + " (expected an interface name of 1.." +
                     std::to_string(IFNAMSIZ - 1) + " characters)");
      cfg.interface = std::string(value);
    } else if (key == "recv_buf_size") {
      once(seen_buf, key);
      int n = -1;
      if (!parse_int(value, n) || n < 0) bad(url, "bad " + shown + " (expected 0.." +
                                                  std::to_string(std::numeric_limits<int>::max()) + ")");
      cfg.recv_buffer_bytes = n;
    } else if (key == "multicast_loop") {
      once(seen_loop, key);
      if (value == "true" || value == "1") cfg.multicast_loop = true;
      else if (value == "false" || value == "0") cfg.multicast_loop = false;
      else bad(url, "bad " + shown + " (expected true, false, 1 or 0)");
    } else {
      bad(url, "unknown option '" + std::string(key) +
                   "' (known: ttl, iface, recv_buf_size, multicast_loop)");
    }
  }
  return cfg;
}

std::string to_url(const GroupConfig& cfg) {
  std::string url = std::string(kScheme) + cfg.address + ":" + std::to_string(cfg.port) +
                    "?ttl=" + std::to_string(cfg.ttl);
  if (!cfg.interface.empty()) url += "&iface=" + cfg.interface;
  url += "&recv_buf_size=" + std::to_string(cfg.recv_buffer_bytes);
  if (!cfg.multicast_loop) url += "&multicast_loop=false";
  return url;
}

}  // namespace lcmx::udpm
