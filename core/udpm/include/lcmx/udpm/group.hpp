#pragma once
// lcmx::udpm::Group — one LCM udpm multicast group on sockets pinned to one interface.

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "lcmx/udpm/config.hpp"
#include "lcmx/udpm/filter.hpp"
#include "lcmx/udpm/keys.hpp"
#include "lcmx/udpm/source.hpp"

namespace lcmx::udpm {

// One complete message. Views are valid only during the on_message callback.
struct Message {
  std::string_view channel;
  std::span<const std::byte> data;
  Source source;
  std::uint32_t sequence = 0;  // the sender's LCM sequence number
  // Sequence numbers of this source that never arrived between its previous message and this
  // one: datagrams the kernel dropped, fragmented messages never completed, loss on the link,
  // and, under a receive filter (filter.hpp), the messages the filter refused.
  // 0 for a source's first message and after a sender restart. A message overtaken by a
  // later one (no reordering happens on one link) counts here and is still delivered.
  std::uint32_t lost_before = 0;
  // A reassembled message's buffer (`data` points into it), null otherwise: on_message may
  // keep it instead of copying `data`.
  std::shared_ptr<const std::byte[]> buffer;
};

struct Counters {
  std::uint64_t packets_received = 0;    // datagrams read from the socket
  std::uint64_t packets_sent = 0;        // datagrams sent
  std::uint64_t messages_received = 0;   // complete messages delivered to on_message
  std::uint64_t messages_sent = 0;       // publish() calls that sent every datagram
  std::uint64_t fragments_received = 0;  // valid LC03 datagrams read
  std::uint64_t incomplete_dropped = 0;  // partial messages expired or evicted
  std::uint64_t malformed_dropped = 0;   // datagrams parse_datagram rejects, inconsistent fragments
  std::uint64_t bytes_received = 0;      // UDP payload bytes read
  std::uint64_t bytes_sent = 0;          // UDP payload bytes sent
  std::uint64_t duplicate_fragments = 0;  // LC03 fragments received twice (ignored)
  std::uint64_t oversize_dropped = 0;    // messages larger than max_reassembly_bytes
  // Datagrams the kernel dropped (SO_RXQ_OVFL), cumulative, as of the last datagram read: a
  // full receive buffer, and also what the socket filter drops by design: this Group's own
  // datagrams (receive_own false) and what the receive filter refuses (set_filter).
  std::uint64_t kernel_dropped = 0;
  std::uint64_t duplicates_dropped = 0;  // messages whose (source, sequence) was delivered already
  // Keyed groups (GroupConfig::keys): datagrams refused before any parsing of the LCM
  // datagram: no envelope, another key, a tag that does not verify (per source: refusals()).
  std::uint64_t unauthenticated_dropped = 0;
  // Valid envelopes received a second time, older than the replay window, or (a sender not
  // heard yet) stamped further than keyed_max_skew from this host's clock.
  std::uint64_t replays_dropped = 0;
  // Datagrams the receive filter (set_filter) refused in user space: those the kernel program
  // let through (queued before the filter changed, an encrypted keyed group, a filter the kernel
  // holds in part), every fragment of an LC03 message refused at its fragment 0, and a
  // reassembled message refused when it completed (counted 1). Not what the kernel dropped.
  std::uint64_t filtered_dropped = 0;
  // Messages sent (publish, publish_routed, publish_counted) on channels past the first
  // Group::kMaxCountedChannels this Group sent on: sent, but not counted per channel.
  std::uint64_t uncounted_sent = 0;
};

// One channel's count of messages sent by this Group (Group::publish_counted).
struct ChannelCount {
  std::string_view channel;
  std::uint64_t messages;  // messages sent on it so far, every datagram of each on the wire
  std::chrono::steady_clock::time_point last_sent;  // when the last of them was sent
};

// Move-only owner of the receive socket (bound to the group's address and port, so unicast to
// the port never reaches it; SO_REUSEADDR and SO_REUSEPORT, so stock liblcm and other Groups
// share the port; joined on the interface) and the send socket (bound to the interface's IPv4
// address and an ephemeral port).
//
// Host-local mode (GroupConfig::interface empty; LCM's default URL has no iface=). liblcm joins
// with INADDR_ANY and sends with no IP_MULTICAST_IF, so the kernel picks the interface the group
// routes to: lo if 224.0.0.0/4 (or the group) routes there, else usually the LAN interface of the
// default route. Its ttl=0 sends never leave the host, but are looped back to this host only as
// arriving on that interface, and only to sockets that joined there (or, for liblcm's own
// receive sockets, IP_MULTICAST_ALL=1: any interface the host joined). So a host-local Group:
//  - joins on lo and on the interface the group routes to (each datagram arrives on one
//    interface, so a socket gets it once however many interfaces it joined; a repeated
//    (source, sequence) is dropped all the same, see duplicates_dropped);
//  - publish() sends on lo (beacons: they keep working whatever happens to the LAN interface);
//  - publish_routed() sends on the routed interface, where every stock program (liblcm's C and
//    C++ programs, Java's lcm-spy) joined, from the same port as publish() (a second source
//    address);
//  - refresh() follows route changes: joins the newly routed interface too, moves
//    publish_routed() there. With no route at all (liblcm refuses to start then) it is lo.
// With ttl=0 nothing leaves the host; joining a LAN interface sends IGMP reports there, as
// liblcm's join does.
//
// Keyed (GroupConfig::keys set): every datagram publish() sends, LC02 or LC03 fragment, is
// sealed into an lcmx envelope (keys.hpp), cut so that the envelope still fits one datagram;
// drain() checks each datagram's envelope first (tag, then the sender's replay window) and
// parses only what it verified. Stock LCM programs ignore the envelopes (unknown magic) and
// are refused.
//
// Threads: drain(), poll(), counters() and the other accessors belong to one thread at a time
// (the "receive thread"). publish() may be called from any number of threads, concurrently with
// each other and with the receive thread. A moved-from Group may only be destroyed or assigned.
class Group {
 public:
  using Handler = std::function<void(const Message&)>;

  // Opens the sockets. Throws: Error(invalid_config) for a bad address (not IPv4 multicast),
  // port 0, ttl outside 0..255, negative buffer size; Error(no_such_interface) when the
  // interface is unknown or has no IPv4 address; Error(system) when a socket call fails (bind,
  // join, ...), with errno.
  static Group open(const GroupConfig& cfg);

  Group(Group&&) noexcept;
  Group& operator=(Group&&) noexcept;
  Group(const Group&) = delete;
  Group& operator=(const Group&) = delete;
  ~Group();

  // Sends one message: one LC02 datagram, or LC03 fragments (see wire.hpp) sent back to back
  // under a lock so fragments of two messages never interleave. Blocks while the socket's send
  // buffer is full. Thread-safe.
  // Throws: Error(channel_too_long) for > 63 bytes, Error(invalid_channel) for a NUL in the
  // channel, Error(message_too_large) for payload > kMaxMessageSize, Error(system) when sending
  // fails (the message may have been partly sent; its sequence number is used up).
  // Returns the LCM sequence number the message was sent with (receivers see it in
  // Message::sequence). Counted per channel once every datagram of it was sent
  // (publish_counted): one hash lookup under the send lock, an allocation only for the first
  // message of a channel.
  std::uint32_t publish(std::string_view channel, std::span<const std::byte> payload);

  // Like publish(), but where stock LCM programs on this host listen: in host-local mode the
  // interface the kernel routes the group to (lo when it routes nowhere); pinned, the same as
  // publish(). Same sequence counter as publish(). Thread-safe; throws and returns as publish().
  std::uint32_t publish_routed(std::string_view channel, std::span<const std::byte> payload);

  // Sends one message on `channel` whose bytes `build` makes, under the send lock, from the
  // counts of every channel this Group sent on (publish, publish_routed and publish_counted,
  // `channel` itself left out; in no particular order): the number of messages sent on each
  // before this one, and when the last was sent. A receiver that counts the messages it got of
  // a channel between two such datagrams of one sender knows exactly how many it lost (no
  // reordering on one link). A message counts once whatever its number of fragments, and only
  // once every datagram of it was sent: a publish that throws is not counted (whatever part of
  // it reached the wire can never be completed by a receiver; its sequence number is used up).
  // Counts are kept for the first kMaxCountedChannels channels sent on; messages of further
  // channels are not counted (Counters::uncounted_sent) and missing from `build`'s counts.
  // `build` runs on the calling thread with the send lock held: it must not publish on this
  // Group; the span and its views are valid during the call only. If it throws, nothing is sent
  // and no sequence number is used. Sent like publish() (not routed). Thread-safe; throws as
  // publish() (the channel is checked before `build` runs, the payload after). Returns the
  // sequence number.
  std::uint32_t publish_counted(std::string_view channel,
                                const std::function<std::vector<std::byte>(std::span<const ChannelCount>)>& build);
  static constexpr std::size_t kMaxCountedChannels = 4096;
  // The per-channel counts as of now (what publish_counted would give `build`, this Group's
  // every channel), copied: to decide whether a counted message is due, not to send the count
  // (it may move before one is sent). Thread-safe (takes the send lock).
  std::vector<std::pair<std::string, std::uint64_t>> channel_counts() const;

  // The sequence number the next message will be sent with (publish/publish_routed). Discovery
  // sends a small marker after data so receivers see a tail loss (docs/discovery.md). Thread-safe.
  std::uint32_t next_sequence() const;

  // Host-local mode: re-reads the route of the group; if it now routes to an interface not yet
  // joined, joins it too (earlier memberships stay), and moves publish_routed() to it. Pinned: no-op.
  // Returns true if anything changed. Receive thread. Never throws (failures are logged).
  bool refresh();

  // The interface publish_routed() sends on (e.g. "eth0", "lo"). Thread-safe.
  std::string routed_interface() const;

  // The receive socket: readable when datagrams are waiting (for poll/epoll). Do not read it.
  int fd() const noexcept;

  // Non-blocking. Reads the datagrams available now in recvmmsg batches (at most 4096 per call,
  // so a flood cannot starve the caller; the fd stays readable if more wait), reassembles LC03
  // fragments per (source, sequence), expires stale partial messages, and calls on_message on
  // this thread for each complete message, in arrival order of its last datagram.
  // Returns the number of messages delivered. If on_message throws, the exception propagates;
  // the datagrams read but not yet handled are handled by the next drain().
  // Throws: Error(system) if recvmmsg fails with something other than EAGAIN/EINTR.
  std::size_t drain(const Handler& on_message);

  // Waits up to `timeout` (negative = 0) for the socket to become readable, then drain().
  // Returns the number of messages delivered (0 on timeout).
  std::size_t poll(std::chrono::milliseconds timeout, const Handler& on_message);

  // The address and port publish()'s packets come from (announced in beacons). publish_routed()
  // sends from the same port and the routed interface's address.
  Source local_source() const;
  // Whether `source` is one of this Group's send sockets (either address, current or past).
  // Receive thread.
  bool is_own(const Source& source) const;

  // A snapshot refreshed at each call; call it from the receive thread.
  const Counters& counters() const noexcept;

  // The group key now in use (null: unkeyed). Thread-safe.
  std::shared_ptr<const GroupKeys> keys() const;
  // Replaces the group key while the Group runs (rotation: the next datagram sent is sealed
  // with keys->keys[0], the next datagram received checked against every key of `keys`).
  // Null makes the group unkeyed; a keyed group's keys must hold 1 or 2 keys. The receive
  // socket's kernel program is derived again (key ids, authenticated or encrypted); if the
  // socket refuses it, the previous one stays (it never drops what user space would take) and
  // a warning is logged.
  // Throws Error(invalid_config) for 0 or more than 2 keys. Thread-safe.
  void set_keys(std::shared_ptr<const GroupKeys> keys);
  // Replaces the receive filter (filter.hpp; a Group opens with the default, which takes
  // everything). The socket's kernel program is replaced at once (atomically: a datagram is
  // judged by the old program or the new one), re-derived from the filter, the own-datagram
  // drop and the group key (set_keys derives it again). drain() applies `f` from its next
  // datagram on, datagrams queued before this call included. Returns kernel_filtered().
  // Receive thread.
  // Throws: Error(invalid_config) for a bad filter (a channel or the control channel not a
  // valid channel name, a mark_prefix longer than kMaxMarkPrefix); Error(system) if the socket
  // refuses even the own-datagram drop. The filter in force is then unchanged.
  bool set_filter(const ReceiveFilter& f);
  // The filter in force. Receive thread.
  const ReceiveFilter& filter() const noexcept;
  // Whether the kernel program holds the whole filter in force (so drain() finds nothing to
  // refuse but datagrams queued before it). False when the group's keys encrypt (the kernel
  // cannot see the channel) or the filter did not fit classic BPF or the kernel's limits (then
  // the kernel holds a part of it, at least the own-datagram drop: filter.hpp). True for the
  // default filter. Thread-safe.
  bool kernel_filtered() const noexcept;

  // What the keyed group refused, per source (GroupConfig::refusals, or the Group's own).
  Refusals& refusals() const noexcept;
  const GroupConfig& config() const noexcept;
  // SO_RCVBUF as the kernel reports it (the kernel doubles the request for bookkeeping).
  int effective_recv_buffer() const noexcept;

 private:
  struct Impl;
  explicit Group(std::unique_ptr<Impl> impl) noexcept;
  std::unique_ptr<Impl> impl_;
};

}  // namespace lcmx::udpm
