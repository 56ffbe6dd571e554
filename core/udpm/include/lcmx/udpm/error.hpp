#pragma once
// lcmx::udpm::Error — the one exception type thrown by lcmx::udpm.

#include <stdexcept>
#include <string>
#include <string_view>

namespace lcmx::udpm {

class Error : public std::runtime_error {
 public:
  enum class Code {
    invalid_config,     // bad URL or GroupConfig field (the message names the bad part)
    no_such_interface,  // interface name unknown, or it has no IPv4 address
    channel_too_long,   // channel name longer than kMaxChannelLength (63) bytes
    message_too_large,  // payload larger than kMaxMessageSize (what LC03 receivers accept)
    system,             // a system call failed; sys_errno() holds errno
    invalid_channel,    // channel name contains a NUL byte (cannot go on the wire)
    bad_key,            // a group key file missing, unreadable, not private, or not a key (named)
  };

  Error(Code code, const std::string& what, int sys_errno = 0);

  Code code() const noexcept { return code_; }
  // errno of the failed system call for Code::system (and some open() failures), else 0.
  int sys_errno() const noexcept { return errno_; }

 private:
  Code code_;
  int errno_;
};

std::string_view to_string(Error::Code code) noexcept;

}  // namespace lcmx::udpm
