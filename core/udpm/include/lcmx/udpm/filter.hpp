#pragma once
// lcmx::udpm::ReceiveFilter — which datagrams a Group's receive socket takes (Group::set_filter).
//
// Why: every process of a vehicle joins the vehicle group, and without a filter the kernel wakes
// every one of them for every datagram of every channel. A filter makes the kernel drop, per
// socket and before the process wakes, the datagrams of channels it does not read and the
// discovery datagrams it does not need (a classic BPF socket filter, SO_ATTACH_FILTER, which an
// unprivileged process may attach; eBPF is not needed).
//
// Contract: a message is delivered by Group::drain() if and only if the filter in force when
// drain() handles it takes it — whatever the kernel did. The kernel program is only a
// shortcut: drain() applies the same rule again to every datagram after its envelope is opened
// and it is parsed (a datagram queued before set_filter, an encrypted keyed group, a filter too
// large for BPF). Datagrams the kernel drops are never read, counted or woken for; those the
// user-space check drops are counted in Counters::filtered_dropped.
//
// The rule, for an LCM datagram of channel C (LC02, or the LC03 message of fragment 0 C):
//   - C == control_channel (non-empty): taken if control_all, else only if it is a *mark*: its
//     payload (the bytes after the channel's NUL) starts with mark_prefix; if mark_channel_at is
//     set, it names, as an LCM string at that offset of the payload (a big-endian int32 length
//     that counts the NUL, the bytes, the NUL), one of `channels` (any channel when `channels`
//     is nullopt); and, if mark_sources is set, its sender is one of them.
//   - any other C: taken if `channels` is nullopt or lists C exactly (every byte and the length:
//     "AB" does not take "ABC" nor "A").
// Not judged (always taken, left to the usual checks): datagrams that are not LC02/LC03
// (counted malformed), and, on a keyed group, anything that is not an envelope of one of its
// keys (refused and reported as before). A keyed group's envelopes that verify are judged by the
// datagram inside. An LC02 datagram whose bytes match no channel taken is dropped by the kernel
// even when it is malformed (then it is not counted malformed).
//
// LC03: the channel travels in fragment 0 only, so the kernel takes every LC03 datagram. drain()
// judges the message at its fragment 0: refused, it drops fragment 0 and every other fragment of
// that (source, sequence) silently (filtered_dropped, never incomplete_dropped); a message whose
// fragment 0 never arrived at all is still counted incomplete (real loss). A message taken at
// fragment 0 is judged again when it completes (the filter may have changed meanwhile).
//
// Loss: a filtered socket does not see every sequence number of a sender, so Message::lost_before
// also counts the messages the filter refused. Receivers that filter settle loss from per-channel
// counts instead (Group::publish_counted's markers).
//
// The kernel program (Group::kernel_filtered() says whether it holds the whole rule): the
// Group's own-datagram drop (GroupConfig::receive_own == false) first, then the rule above on
// LC02 datagrams — at offset 0, or after the 32-byte envelope header of an authenticated
// envelope of one of the group's keys (its tag is checked in user space only: such an envelope
// of a refused channel is dropped unverified, so a forger's datagrams on channels this process
// does not read are not counted in refusals; those of another key or no key always reach user
// space and are refused and reported). Encrypted envelopes are opaque to the kernel: on a group
// whose keys encrypt, only user space applies the rule (kernel_filtered() false). What the
// kernel drops is counted in Counters::kernel_dropped (the socket's drop count).
// Limits: BPF's 4096 instructions and 8-bit conditional jumps (every jump stays within one
// channel's block: unlimited by the jumps) and the kernel's net.core.optmem_max. A channel of
// n bytes takes 3 + 2 x (number of 4-, 2- and 1-byte compares of its n + 1 bytes, NUL included)
// instructions (twice with mark_channel_at: the marks' names are compared too, plus 2), a mark
// source 5, the rest about 30: 116 channels of 63 bytes fit, 371 of 12 to 15 bytes, 453 of 6
// bytes (about half as many with mark_channel_at), or 813 mark sources. A filter too large is
// attached in part, in this order as long as it does not fit: without `channels` (every other
// channel taken by the kernel, and marks whatever channel they name), without `mark_sources`,
// then the own-datagram drop alone; user space applies the rest (Counters::filtered_dropped).
//
// Regular type; default-constructed: takes everything (no filter). Group::set_filter checks it.

#include <cstddef>
#include <optional>
#include <string>
#include <vector>

#include "lcmx/udpm/source.hpp"

namespace lcmx::udpm {

inline constexpr std::size_t kMaxMarkPrefix = 16;  // bytes

struct ReceiveFilter {
  // Exact channel names taken (valid channel names, wire.hpp; duplicates allowed). nullopt:
  // every channel. An empty list: none (but the control channel, as it says).
  std::optional<std::vector<std::string>> channels;
  // A channel judged apart from `channels` (lcmx: discovery's "LCMX_BEACON"); empty: none.
  std::string control_channel;
  // The control channel's datagrams: every one (control_all), or only marks: those whose payload
  // starts with `mark_prefix` (at most kMaxMarkPrefix bytes; empty: every datagram of it) and,
  // if `mark_sources` is set, come from one of them (address and port).
  bool control_all = true;
  std::vector<std::byte> mark_prefix;  // e.g. an lcm-gen type's 8-byte fingerprint
  // A mark names a channel at this offset of its payload (lcmx: marker_t.channel, after its
  // fingerprint, version, participant and host: 28), and is taken only for a channel taken.
  std::optional<std::size_t> mark_channel_at;
  std::optional<std::vector<Source>> mark_sources;
  friend bool operator==(const ReceiveFilter&, const ReceiveFilter&) = default;
};

// True when `f` takes every datagram (the default, no filter at all).
bool takes_everything(const ReceiveFilter& f) noexcept;

}  // namespace lcmx::udpm
