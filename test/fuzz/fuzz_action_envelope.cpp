// libFuzzer target: action envelopes (lcmtypes/action.lcm: what action servers and clients
// read from the network or shared memory, core/src/action.cpp) through the checked decoders
// (envelope_fuzz.hpp says what is checked). The first byte picks the type.
#include "envelope_fuzz.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size < 1) return 0;
  const std::span<const std::byte> in(reinterpret_cast<const std::byte*>(data) + 1, size - 1);
  using namespace lcmx_msgs;
  switch (data[0] % 7) {
    case 0: envelope_fuzz::check<action_goal_t>(in); break;
    case 1: envelope_fuzz::check<action_goal_reply_t>(in); break;
    case 2: envelope_fuzz::check<action_goal_ref_t>(in); break;
    case 3: envelope_fuzz::check<action_goal_status_t>(in); break;
    case 4: envelope_fuzz::check<action_result_t>(in); break;
    case 5: envelope_fuzz::check<action_feedback_t>(in); break;
    default: envelope_fuzz::check<action_status_t>(in); break;
  }
  return 0;
}
