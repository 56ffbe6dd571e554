// Core's use of the shm liveness API across processes (issue 10): a shm publisher in another
// pid namespace (a container sharing /dev/shm and the network) killed -9 is noticed through
// shm::OwnerWatch, not after its lease; a segment file others may write is refused with an
// error Event and nothing is delivered from it.
#include <signal.h>
#include <sys/stat.h>

#include <algorithm>

#include "lcmx/core.hpp"
#include "containers.hpp"
#include "dead_shm.hpp"
#include "support.hpp"

using namespace lcmx::it;

namespace {

// argv running the test peer in new pid + mount namespaces (private /proc), sharing /dev/shm
// and the network namespace: a container started with --ipc=host --net=host.
std::vector<std::string> in_pid_namespace(std::vector<std::string> peer_args) {
  return lcmx::it::in_container({"--pid", "--fork", "--kill-child", "--mount-proc", "--propagation", "private"}, false,
                      LCMX_TEST_PEER, std::move(peer_args));
}

bool can_unshare_pid() {
  Child c({LCMX_UNSHARE, "--pid", "--fork", "--mount-proc", "--propagation", "private", "/bin/true"}, {}, true);
  return c.wait(10000ms) == 0;
}

}  // namespace

TEST_CASE("a shm publisher in another pid namespace killed -9 is noticed at once - not after its lease",
          "[integration][lifecycle][containers]") {
  if (!can_unshare_pid()) {
    LCMX_SKIP("cannot create pid namespaces here");
  }
  struct RemovePid1 {  // after the Session: what the killed publisher (pid 1 there) left
    ~RemovePid1() { remove_dead_shm_of(1); }
  } remove_pid1;
  // Leases 5 s: a departure noticed well before that is the writer's death (OwnerWatch).
  Session s(45, 30000ms);
  const auto long_lease = s.env(100ms, 5000ms);
  const auto ch = unique_channel("PIDNS_KILLED", 45);
  auto& sub = s.peer({"sub", "--channel", ch, "--type", "pose", "--publishers", "1"}, long_lease);
  REQUIRE(sub.expect("READY"));
  auto& pub = s.spawn(in_pid_namespace({"pub", "--channel", ch, "--type", "pose", "--count", "0", "--rate", "200",
                                        "--subscribers", "1"}),
                      long_lease);
  REQUIRE(sub.expect("MATCHED", 10000ms));
  const auto killed_at = Clock::now();
  pub.kill9();  // unshare, and with it (--kill-child) the publisher, pid 1 of its namespace
  REQUIRE(sub.wait_seen("EVENT publisher_unmatched " + ch, 4000ms));
  const auto took = std::chrono::duration_cast<ms>(Clock::now() - killed_at);
  std::fprintf(stderr, "kill -9 in another pid namespace -> publisher_unmatched seen: %lld us (lease 5000 ms)\n",
               static_cast<long long>(std::chrono::duration_cast<std::chrono::microseconds>(Clock::now() - killed_at).count()));
  CHECK(took < 1000ms);
  INFO(sub.output());
  CHECK_FALSE(sub.seen("EVENT participant_left"));  // its lease has not run out: not that path
}

TEST_CASE("a publisher's segment file that others may write is refused: an error Event and nothing delivered",
          "[integration][lifecycle]") {
  Session s(46, 30000ms);
  const auto ch = unique_channel("UNTRUSTED", 46);
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "pose", "--count", "0", "--rate", "100"});
  REQUIRE(pub.expect("READY"));
  const auto segments = shm_segments_of(pub.pid());
  REQUIRE(!segments.empty());
  // Anyone on the host could now truncate or rewrite it under a reader: not mapped.
  for (const auto& n : segments) REQUIRE(::chmod(("/dev/shm/" + n).c_str(), 0666) == 0);
  auto& sub = s.peer({"sub", "--channel", ch, "--type", "pose"});
  REQUIRE(sub.expect("READY"));
  REQUIRE(sub.wait_seen("EVENT error " + ch, 5000ms));
  const auto fin = of(sub.summaries("quit"), ch);
  CHECK(sub.wait() == 0);  // no crash
  INFO(sub.output());
  CHECK(sub.text().find("writable by others") != std::string::npos);
  CHECK_FALSE(sub.seen("EVENT publisher_matched"));
  CHECK(fin.num("received") == 0);
}
