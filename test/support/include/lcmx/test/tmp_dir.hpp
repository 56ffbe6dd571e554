// For Catch2 tests that write files: TmpDir, a fresh directory under /tmp removed with
// everything in it when the test leaves its scope, failed or not. Header-only
// (lcmx::test_headers); each test program names its directories by its own prefix.
#pragma once

#include <catch2/catch.hpp>
#include <sys/stat.h>
#include <sys/types.h>
#include <unistd.h>

#include <cstdlib>  // mkdtemp
#include <filesystem>
#include <fstream>
#include <string>

namespace lcmx::test {

struct TmpDir {
  std::string path;
  // /tmp/<prefix>_XXXXXX with `mode` (mkdtemp's 0700 unless a test's peers, e.g. stock LCM
  // tools run as another user, must write into it). Fails the test if it cannot be made.
  explicit TmpDir(const std::string& prefix, mode_t mode = 0700) {
    std::string t = "/tmp/" + prefix + "_XXXXXX";
    REQUIRE(::mkdtemp(t.data()) != nullptr);
    path = t;
    if (mode != 0700) ::chmod(path.c_str(), mode);
  }
  ~TmpDir() {
    std::error_code ec;  // a destructor must not throw; a leftover shows in /tmp
    std::filesystem::remove_all(path, ec);
  }
  TmpDir(const TmpDir&) = delete;
  TmpDir& operator=(const TmpDir&) = delete;
  std::string file(const std::string& name) const { return path + "/" + name; }
  // Writes `text` into the file `name` here; returns its path.
  std::string write(const std::string& name, const std::string& text) const {
    std::ofstream(file(name)) << text;
    return file(name);
  }
};

}  // namespace lcmx::test
