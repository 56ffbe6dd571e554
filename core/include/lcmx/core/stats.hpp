// Statistics and events visible to users.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

namespace lcmx {

// Which path a publisher->subscriber pair uses (DESIGN.md "Delivery").
enum class Path { intra, shm, udp, bridge };
const char* to_string(Path p);

struct PairStats {
  std::uint64_t publisher_participant = 0;
  std::uint64_t publisher_endpoint = 0;
  Path path = Path::intra;
  std::uint64_t received = 0;
  std::uint64_t drops = 0;
};

struct PublisherStats {
  std::uint64_t published = 0;    // publish() calls that completed (every path)
  // Messages no subscriber of other processes got because every shared-memory slot was
  // pinned by lagging zero-copy readers (shm::Writer::dropped()); those subscribers count
  // them in their drops too. publish() never throws for this.
  std::uint64_t shm_dropped = 0;
};

struct SubscriberStats {
  std::uint64_t delivered = 0;      // callbacks run
  std::uint64_t drops = 0;          // lost over all pairs
  std::uint64_t decode_errors = 0;  // bytes that did not decode as the subscribed type
  std::vector<PairStats> publishers;
  std::vector<std::string> errors;  // e.g. type mismatches with publishers on the channel
};

// One UDP group of this participant (Runtime::udp_stats): what its socket took and what its
// receive filter kept away (docs/ARCHITECTURE.md "Receive filter").
struct UdpGroupStats {
  bool open = false;                   // the group exists (the vehicle group only with vehicle_url)
  std::uint64_t packets_received = 0;  // datagrams read (each woke this process or was read in a batch)
  std::uint64_t messages_received = 0;
  std::uint64_t packets_sent = 0;
  std::uint64_t filtered_dropped = 0;  // refused by the filter after they were read (user space)
  std::uint64_t kernel_dropped = 0;    // dropped by the kernel: a full buffer, own datagrams, the filter
  bool kernel_filtered = false;        // the kernel applies the whole filter
  bool all_channels = true;            // the filter takes every channel
  std::size_t channels = 0;            // else: the channels it takes
  bool discovery = true;               // it takes the group's discovery datagrams
  bool markers_by_channel = false;     // it takes only the data markers of the channels it reads
};
struct UdpStats {
  UdpGroupStats host_local, vehicle;
};

struct Event {
  enum class Kind {
    type_mismatch,        // same channel, different fingerprint: not matched
    publisher_matched,    // a subscriber of ours now receives from a publisher
    publisher_unmatched,  // ... no longer (publisher gone, lease expired)
    participant_joined,
    participant_left,
    // A fault lcmx survived at run time: an exception on an executor thread, a publisher's
    // shared memory that cannot be opened (the pair then uses another path or none). The
    // message says what.
    error,
  };
  Kind kind;
  std::string channel;  // empty for participant events
  std::string message;  // human-readable, also logged
};
// "type_mismatch", "publisher_matched", ... (the enumerator's name), for logs and tools.
const char* to_string(Event::Kind k);

}  // namespace lcmx
