// libFuzzer target: the Message Bridge's status (lcmtypes/bridge.lcm, read by `lcmx bridge
// status` from the host-local group) through the checked decoders (envelope_fuzz.hpp says
// what is checked). The first byte picks the type.
#include "envelope_fuzz.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size < 1) return 0;
  const std::span<const std::byte> in(reinterpret_cast<const std::byte*>(data) + 1, size - 1);
  using namespace lcmx_msgs;
  switch (data[0] % 4) {
    case 0: envelope_fuzz::check<bridge_status_t>(in); break;
    case 1: envelope_fuzz::check<bridge_peer_status_t>(in); break;
    case 2: envelope_fuzz::check<bridge_link_status_t>(in); break;
    default: envelope_fuzz::check<bridge_channel_status_t>(in); break;
  }
  return 0;
}
