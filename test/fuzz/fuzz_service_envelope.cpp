// libFuzzer target: service envelopes (lcmx_msgs::service_request_t / service_reply_t: what a
// server and a client read from the network or shared memory, core/src/service.cpp), both the
// owning decoders (envelope_fuzz.hpp) and the in-place views services use: a view decode
// accepts exactly what the owning one accepts, its payload lies inside the input, and its
// header re-encodes to the input's bytes. The first byte picks the type.
#include <algorithm>
#include <cstring>

#include "envelope_fuzz.hpp"

namespace {

template <class T, class Header>
void check_view(std::span<const std::byte> in) {
  const bool owning = envelope_fuzz::check<T>(in);
  Header h;
  std::span<const std::byte> payload;
  const bool view = lcmx::lcmtypes::decode(in, h, payload);
  ENVELOPE_CHECK(view == owning);
  if (!view) return;
  ENVELOPE_CHECK(payload.data() >= in.data() && payload.data() + payload.size() == in.data() + in.size());
  const std::size_t header = lcmx::lcmtypes::header_size(h);
  ENVELOPE_CHECK(header + payload.size() == in.size());
  std::vector<std::byte> out(header);
  ENVELOPE_CHECK(lcmx::lcmtypes::encode_header(h, payload.size(), out));
  ENVELOPE_CHECK(std::equal(out.begin(), out.end(), in.begin()));
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size < 1) return 0;
  const std::span<const std::byte> in(reinterpret_cast<const std::byte*>(data) + 1, size - 1);
  if (data[0] % 2 == 0) check_view<lcmx_msgs::service_request_t, lcmx::lcmtypes::ServiceRequestHeader>(in);
  else check_view<lcmx_msgs::service_reply_t, lcmx::lcmtypes::ServiceReplyHeader>(in);
  return 0;
}
