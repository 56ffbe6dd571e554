// Child roles of lcmx_bench_bridge (see roles.cpp). The orchestrator (main.cpp) starts each
// role as a copy of this binary inside an emulated host's network namespace.
//
// Protocol (the harness's RoleProcess), one text line per write():
//  - fd 3 (kReportFd, child -> orchestrator): "ready", "error <text>", "note <text>", "done";
//    publishers: "s <seq>" once a message is handed to the transport, "streamed <n> <t0> <t1>";
//    subscribers: "r <seq> <size> <send_ns> <recv_ns>" for every message: the callback only
//    appends a record in memory, a reporter thread writes the lines every 5 ms.
//  - fd 4 (kCmdFd, orchestrator -> child): "send <seq> <size>", "stream <size> <count> <hz>
//    <first k>", "quit" (publishers); "quit" (subscribers). EOF = quit.
// Every message starts with a Header (seq, send_ns, size); the rest is payload that is never
// rewritten per message (the publisher side writes 24 bytes, the transport moves `size`).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

namespace lcmxbench::bridge {

struct Header {
  std::int64_t seq;
  std::int64_t send_ns;  // CLOCK_MONOTONIC right before the message is handed to the transport
  std::int64_t size;     // bytes of the whole message, header included
};
static_assert(sizeof(Header) == 24);

struct ChildConfig {
  std::string role;                    // {zmq,lcmx,floor}-{pub,sub}
  std::vector<std::string> endpoints;  // zmq-pub: connect to each; zmq-sub: bind endpoints[0]
  std::string channel;                 // lcmx roles
  std::string discovery_url;           // lcmx roles
  std::string wait = "block";          // lcmx-sub executor wait strategy: block | spin | adaptive | busy
  std::size_t max_size = 0;            // largest message of the run
};

int run_zmq_pub(const ChildConfig& c);
int run_zmq_sub(const ChildConfig& c);
int run_lcmx_pub(const ChildConfig& c);
int run_lcmx_sub(const ChildConfig& c);
// The platform floor of experiment 3: floor-pub (on host B) writes the header into a shared
// page, bumps a futex word and FUTEX_WAKEs every floor-sub (no data, no network).
int run_floor_pub(const ChildConfig& c);
int run_floor_sub(const ChildConfig& c);

}  // namespace lcmxbench::bridge
