// lcmx core errors. The core layer reports real faults by throwing lcmx::Error; "no data
// yet" and "would block" are never errors (std::optional / bool results instead).
#pragma once

#include <stdexcept>
#include <string>

namespace lcmx {

enum class Errc {
  invalid_argument,   // bad name, bad option value
  channel_too_long,   // LCM channel names are at most 63 bytes
  message_too_large,  // message over the topic's configured maximum
  type_mismatch,      // same channel, different lcm-gen fingerprint
  already_exists,     // a second Runtime in one process
  transport,          // shared memory / socket failure (message says which)
};

class Error : public std::runtime_error {
 public:
  Error(Errc code, const std::string& what) : std::runtime_error(what), code_(code) {}
  Errc code() const noexcept { return code_; }

 private:
  Errc code_;
};

inline constexpr std::size_t kMaxChannelLength = 63;  // LCM's limit, in bytes

}  // namespace lcmx
