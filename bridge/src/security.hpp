// CURVE authentication, the pure part: the ZAP handler's answer to one request (security.cpp
// runs the ZAP thread; unit tests: test/bridge/pieces_test.cpp). Only the CURVE mechanism with
// the public key of a configured peer is admitted, as that peer (its name is the User-Id that
// the channel and control threads compare with the routing id).
#pragma once

#include <cstddef>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "lcmx/bridge/config.hpp"

namespace lcmx::bridge::security {

struct ZapAnswer {
  std::string status;  // "200" admitted, "400" refused
  std::string text;
  std::string user;    // the peer's name when admitted
  std::string key;     // the client's public key in Z85 ("" unless CURVE with a 32-byte key)
};

ZapAnswer zap_decide(std::string_view mechanism, std::span<const std::byte> client_key,
                     const std::vector<PeerConfig>& peers);

}  // namespace lcmx::bridge::security
