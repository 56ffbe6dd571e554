// lcmx_netns_holder HOSTS [watchdog]: creates an emulation, starts `sleep` inside host 0, prints
// "ready <ns of host 0> <ns of switch>" and waits until killed
// (with "watchdog": until a 200 ms Watchdog fires and aborts). Used by the crash-cleanup test.
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <exception>
#include <string>

#include "lcmx/test/netns.hpp"
#include "lcmx/test/watchdog.hpp"

int main(int argc, char** argv) {
  try {
    lcmx::test::EmulationSpec spec;
    spec.hosts = argc > 1 ? std::atoi(argv[1]) : 2;
    auto emu = lcmx::test::Emulation::create(spec);
    auto child = emu.spawn(0, {"sleep", "600"});
    std::printf("ready %s %s %d\n", emu.ns(0).c_str(), emu.switch_ns().c_str(), child.pid());
    std::fflush(stdout);
    if (argc > 2 && std::string(argv[2]) == "watchdog") {
      lcmx::test::Watchdog wd(std::chrono::milliseconds(200), "holder");
      for (int i = 0; i < 600; ++i) ::pause();  // the watchdog aborts the process
    }
    for (int i = 0; i < 600; ++i) ::pause();  // until a signal kills us
  } catch (const std::exception& e) {
    std::printf("error %s\n", e.what());
    return 1;
  }
}
