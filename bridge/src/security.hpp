// Who may connect, the pure part: the ZAP handler's answer to one request (security.cpp runs
// the ZAP thread; unit tests: test/bridge/pieces_test.cpp). Every ROUTER of a bridge asks it,
// with or without CURVE (docs/bridge.md "Trust"):
//  - without CURVE (the NULL mechanism), a connection is admitted only from an address that is
//    one of a configured peer's endpoint addresses, as that peer (config refuses an address
//    shared by two peers, so the address names one);
//  - with CURVE, only with a configured peer's public key, as that peer, and only from one of
//    that peer's addresses.
// The peer's name is the User-Id that the channel and control threads compare with the name a
// message claims (its routing id, the `from` of a ping): a peer cannot speak in another's name.
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
  std::string text;    // ZAP status text
  std::string user;    // the peer's name when admitted
  std::string key;     // the client's public key in Z85 ("" unless CURVE with a 32-byte key)
  std::string reason;  // refused: why, for the log line (names the address)
};

// `address`: the connecting peer's IP address as ZAP gives it. `curve`: whether this bridge
// runs CURVE (then only the CURVE mechanism is admitted; without it only NULL).
ZapAnswer zap_decide(std::string_view mechanism, std::span<const std::byte> client_key, std::string_view address,
                     bool curve, const std::vector<PeerConfig>& peers);

}  // namespace lcmx::bridge::security
