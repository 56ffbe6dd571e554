#include "lcmx/discovery/identity.hpp"
#include "lcmx/shm/liveness.hpp"

#include <sys/stat.h>
#include <unistd.h>

#include <cstdlib>
#include <fstream>
#include <random>
#include <sstream>
#include <stdexcept>

namespace lcmx::discovery {
namespace {

std::string read_first_line(const char* path) {
  std::ifstream f(path);
  std::string line;
  std::getline(f, line);
  return line;
}

// FNV-1a 64: stable across runs and builds (std::hash is not).
std::uint64_t fnv1a(std::string_view s, std::uint64_t h = 0xcbf29ce484222325ull) {
  for (unsigned char c : s) {
    h ^= c;
    h *= 0x100000001b3ull;
  }
  return h;
}

}  // namespace

std::uint64_t host_id() {
  if (const char* env = std::getenv("LCMX_HOST_ID"); env && *env) {
    char* end = nullptr;
    errno = 0;
    const unsigned long long v = std::strtoull(env, &end, 0);
    if (errno != 0 || end == env || *end != '\0' || v == 0)
      throw std::invalid_argument(std::string("LCMX_HOST_ID='") + env +
                                  "' is not a non-zero decimal or 0x-hex number");
    return v;
  }
  std::string machine = read_first_line("/etc/machine-id");
  if (machine.empty()) machine = read_first_line("/proc/sys/kernel/random/boot_id");
  struct stat st {};
  std::uint64_t netns = 0;
  // thread-self: a thread that entered another namespace (setns) is on that host.
  if (::stat("/proc/thread-self/ns/net", &st) == 0 || ::stat("/proc/self/ns/net", &st) == 0)
    netns = static_cast<std::uint64_t>(st.st_ino);
  // The /dev/shm this process sees (shm::shm_domain_id: device + inode): containers that
  // share the network namespace but not /dev/shm cannot use each other's shared memory, so
  // they are two hosts.
  std::uint64_t h = fnv1a(machine);
  h = fnv1a(std::to_string(netns), h);
  h = fnv1a(std::to_string(shm::shm_domain_id()), h);
  return h == 0 ? 1 : h;
}

std::uint64_t random_participant_id() {
  std::random_device rd;
  std::uint64_t v = 0;
  while (v == 0) v = ((static_cast<std::uint64_t>(rd()) << 32) | rd()) & 0x7fffffffffffffffull;
  return v;
}

std::string process_name() { return read_first_line("/proc/self/comm"); }

std::uint64_t pid_namespace() {
  struct stat st {};
  if (::stat("/proc/self/ns/pid", &st) != 0) return 0;
  return static_cast<std::uint64_t>(st.st_ino);
}

std::uint64_t process_start_time(int pid) {
  std::ifstream f("/proc/" + std::to_string(pid) + "/stat");
  std::string s((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  // comm may contain spaces and parentheses: fields resume after the last ')'.
  const auto close = s.rfind(')');
  if (close == std::string::npos) return 0;
  std::istringstream in(s.substr(close + 2));
  std::string field;
  // After ')' come field 3 (state) ... field 22 (starttime): skip 19, read the 20th.
  for (int i = 3; i < 22; ++i) in >> field;
  std::uint64_t start = 0;
  in >> start;
  return start;
}

}  // namespace lcmx::discovery
