// lcmx_netns_holder HOSTS [watchdog]: creates an emulation, starts `sleep` inside host 0, prints
// "ready <ns of host 0> <ns of switch> <sleep's pid> <ns of host 1> ..." and waits until killed
// (with "watchdog": until a 200 ms Watchdog fires and aborts). SIGTERM/SIGINT end it cleanly
// (the namespaces are removed). Used by the crash-cleanup test and the Python multi-host tests.
#include <signal.h>
#include <unistd.h>

#include <cstdio>
#include <ctime>
#include <cstdlib>
#include <exception>
#include <string>

#include "lcmx/test/netns.hpp"
#include "lcmx/test/watchdog.hpp"

namespace {
volatile sig_atomic_t g_stop = 0;
}

int main(int argc, char** argv) {
  struct sigaction sa {};
  sa.sa_handler = [](int) { g_stop = 1; };
  sigaction(SIGTERM, &sa, nullptr);
  sigaction(SIGINT, &sa, nullptr);
  try {
    lcmx::test::EmulationSpec spec;
    spec.hosts = argc > 1 ? std::atoi(argv[1]) : 2;
    auto emu = lcmx::test::Emulation::create(spec);
    auto child = emu.spawn(0, {"sleep", "600"});
    std::printf("ready %s %s %d", emu.ns(0).c_str(), emu.switch_ns().c_str(), child.pid());
    for (int h = 1; h < spec.hosts; ++h) std::printf(" %s", emu.ns(h).c_str());
    std::printf("\n");
    std::fflush(stdout);
    if (argc > 2 && std::string(argv[2]) == "watchdog") {
      lcmx::test::Watchdog wd(std::chrono::milliseconds(200), "holder");
      for (int i = 0; i < 600; ++i) ::pause();  // the watchdog aborts the process
    }
    // Until a signal kills or stops us (at most 10 min). Checked every 100 ms: pause() could
    // miss a SIGTERM that lands between the check and the call.
    for (int i = 0; i < 6000 && !g_stop; ++i) {
      timespec ts{0, 100'000'000};
      ::nanosleep(&ts, nullptr);
    }
  } catch (const std::exception& e) {
    std::printf("error %s\n", e.what());
    return 1;
  }
}
