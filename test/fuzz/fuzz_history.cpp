// libFuzzer target: keep-last-N replays (lcmx_msgs::history_t, received by every runtime on
// its UDP groups, core/src/udp_receive.cpp on_history) and their messages, through the checked
// decoder (envelope_fuzz.hpp says what is checked). The first byte picks the type.
#include "envelope_fuzz.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size < 1) return 0;
  const std::span<const std::byte> in(reinterpret_cast<const std::byte*>(data) + 1, size - 1);
  if (data[0] % 2 == 0) envelope_fuzz::check<lcmx_msgs::history_t>(in);
  else envelope_fuzz::check<lcmx_msgs::history_message_t>(in);
  return 0;
}
