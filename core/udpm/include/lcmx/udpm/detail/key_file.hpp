#pragma once
// Key files on disk, the one implementation for lcmx's group keys (udpm keys.cpp) and the
// bridge's CURVE keys (bridge config.cpp): read with type, size, owner and mode checked on the
// file opened; written to a new file renamed (or linked) into place, never through a symbolic
// link. Installed, not stable (detail/).
//
// These functions throw nothing of their own: each returns a KeyFileProblem whose text is to
// follow "<the file>: " in the caller's message, and the caller throws its own error (the
// bridge a ConfigError, udpm an Error(bad_key)).

#include <sys/types.h>

#include <cstddef>
#include <optional>
#include <string>
#include <string_view>
#include <variant>

namespace lcmx::udpm::detail {

struct KeyFileProblem {
  std::string why;  // e.g. "cannot read: No such file or directory"
};

// Who may own a key file, and who else may touch it.
enum class KeyFileAccess {
  // owned by this process's effective user, no group or other permission bits (mode 0600 or
  // stricter): a secret (a group key, a CURVE secret key).
  owner_only,
  // owned by this user or root, writable by nobody else: a public key (whoever can write it
  // can make its reader trust another key).
  public_key,
};

// How a caller names its key files in messages.
struct KeyFileWords {
  std::string_view noun;     // "a group key", "a secret key", "a public key"
  std::string_view made_by;  // "`lcmx keygen --group`": what writes such files
};

// The bytes of the key file `path` (a symbolic link is followed): a regular file of at most
// `max_bytes` whose owner and mode `access` allows, checked with fstat on the opened file (no
// race with a rename meanwhile). Not an ifstream: a device or FIFO is refused, never read
// without end. Returns: the bytes, or the problem (cannot read, not a key file, owner or mode,
// larger than max_bytes by the time it was read).
std::variant<std::string, KeyFileProblem> read_key_file_bytes(const std::string& path, KeyFileAccess access,
                                                              KeyFileWords words, std::size_t max_bytes);

// Whether a key file may be written at `path`: nothing there, or a regular file and
// `overwrite` (a symbolic link or anything but a regular file is refused, overwrite or not).
// `exists_hint` follows the "cannot create: File exists" of an existing file without
// `overwrite` (e.g. " (--force replaces it)"). Returns: nullopt, or the problem.
std::optional<KeyFileProblem> check_key_file_target(const std::string& path, bool overwrite,
                                                    std::string_view exists_hint = {});

// Writes `text` to a new file (mkostemp, O_EXCL) beside `path`, with `mode`, fsynced, then
// renamed over `path` (`overwrite`: a rename replaces the directory entry, never what a link
// there points to) or linked to its name (fails with EEXIST if the name appeared meanwhile:
// no race). The temporary file never remains. Check the target first (check_key_file_target).
// Returns: nullopt, or the problem ("cannot create: ...", "write failed: ...").
std::optional<KeyFileProblem> write_key_file_bytes(const std::string& path, std::string_view text, mode_t mode,
                                                   bool overwrite);

}  // namespace lcmx::udpm::detail
