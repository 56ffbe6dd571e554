#include "lcmx/udpm/error.hpp"

namespace lcmx::udpm {

Error::Error(Code code, const std::string& what, int sys_errno)
    : std::runtime_error(what), code_(code), errno_(sys_errno) {}

std::string_view to_string(Error::Code code) noexcept {
  switch (code) {
    case Error::Code::invalid_config: return "invalid_config";
    case Error::Code::no_such_interface: return "no_such_interface";
    case Error::Code::channel_too_long: return "channel_too_long";
    case Error::Code::message_too_large: return "message_too_large";
    case Error::Code::system: return "system";
    case Error::Code::invalid_channel: return "invalid_channel";
    case Error::Code::bad_key: return "bad_key";
  }
  return "unknown";
}

}  // namespace lcmx::udpm
