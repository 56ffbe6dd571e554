// Keyed groups (lcmx/udpm/keys.hpp, docs/keyed-groups.md): key files, the envelope, the
// replay window, and keyed Groups on lo (each test its own group and port) against unkeyed
// senders, wrong keys, replays, rotation, and stock liblcm in a network namespace.
#include <fcntl.h>
#include <sys/stat.h>

#include <sodium.h>

#include <catch2/catch.hpp>
#include <ctime>
#include <filesystem>
#include <fstream>

#include "envelope.hpp"
#include "support.hpp"

using namespace lcmx::udpm;
using namespace lcmx::udpm::test;

namespace {

std::shared_ptr<const GroupKeys> keys_of(std::vector<GroupKey> k, bool encrypt = false) {
  auto g = std::make_shared<GroupKeys>();
  g->keys = std::move(k);
  g->encrypt = encrypt;
  return g;
}

GroupKey fixed_key(std::uint8_t fill) {
  std::array<std::uint8_t, kKeySize> b{};
  for (std::size_t i = 0; i < b.size(); ++i) b[i] = static_cast<std::uint8_t>(fill + i);
  return make_key(b);
}

// True if `envelope`, sealed from `inner` with keys.keys.front(), holds the bytes of libsodium's
// XChaCha20-Poly1305-IETF under nonce sender | 0^8 | counter (the envelope computes it as
// HChaCha20 once per sender, a one-time key made ahead, then Poly1305: docs/keyed-groups.md).
bool libsodium_agrees(const std::vector<std::byte>& envelope, std::string_view inner, const GroupKeys& keys) {
  REQUIRE(envelope.size() == kEnvelopeOverhead + inner.size());
  unsigned char nonce[24] = {};
  std::memcpy(nonce, envelope.data() + 16, 8);
  std::memcpy(nonce + 16, envelope.data() + 24, 8);
  std::vector<unsigned char> body(inner.size()), tag(kEnvelopeTagSize);
  const auto* header = reinterpret_cast<const unsigned char*>(envelope.data());
  const auto* key = keys.keys.front().bytes.data();
  bool same = true;
  if (keys.encrypt) {
    crypto_aead_xchacha20poly1305_ietf_encrypt_detached(body.data(), tag.data(), nullptr,
                                                        reinterpret_cast<const unsigned char*>(inner.data()),
                                                        inner.size(), header, kEnvelopeHeaderSize, nullptr, nonce, key);
    same = std::memcmp(body.data(), envelope.data() + kEnvelopeHeaderSize, body.size()) == 0;
  } else {
    unsigned char none = 0;
    crypto_aead_xchacha20poly1305_ietf_encrypt_detached(&none, tag.data(), nullptr, &none, 0, header,
                                                        kEnvelopeHeaderSize + inner.size(), nullptr, nonce, key);
  }
  return same && std::memcmp(tag.data(), envelope.data() + kEnvelopeHeaderSize + inner.size(), tag.size()) == 0;
}

// `inner` sealed by `sealer` with `keys`.
std::vector<std::byte> sealed(lcmx::udpm::detail::Sealer& sealer, const GroupKeys& keys, std::string_view inner) {
  std::vector<std::byte> buf(kEnvelopeOverhead + inner.size());
  std::memcpy(buf.data() + kEnvelopeHeaderSize, inner.data(), inner.size());
  REQUIRE(sealer.seal(keys, buf.data(), inner.size()) == buf.size());
  return buf;
}

// A temporary directory, removed at the end of the test.
struct TmpDir {
  std::filesystem::path path;
  TmpDir() {
    std::string t = (std::filesystem::temp_directory_path() / "lcmx_keyed_XXXXXX").string();
    REQUIRE(::mkdtemp(t.data()) != nullptr);
    path = t;
  }
  ~TmpDir() {
    std::error_code ec;
    std::filesystem::remove_all(path, ec);
  }
};

std::string key_error(const std::string& path) {
  try {
    (void)read_key_file(path);
  } catch (const Error& e) {
    CHECK(e.code() == Error::Code::bad_key);
    return e.what();
  }
  FAIL("read_key_file did not throw");
  return {};
}

// A socket that receives the group's datagrams raw (as a LAN machine capturing them would).
class Capture {
 public:
  explicit Capture(const GroupConfig& cfg) {
    fd_ = ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
    REQUIRE(fd_ >= 0);
    const int one = 1;
    REQUIRE(::setsockopt(fd_, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one) == 0);
    REQUIRE(::setsockopt(fd_, SOL_SOCKET, SO_REUSEPORT, &one, sizeof one) == 0);
    sockaddr_in a{};
    a.sin_family = AF_INET;
    REQUIRE(::inet_pton(AF_INET, cfg.address.c_str(), &a.sin_addr) == 1);
    a.sin_port = htons(cfg.port);
    REQUIRE(::bind(fd_, reinterpret_cast<sockaddr*>(&a), sizeof a) == 0);
    ip_mreqn m{};
    m.imr_multiaddr = a.sin_addr;
    m.imr_ifindex = static_cast<int>(::if_nametoindex("lo"));
    REQUIRE(::setsockopt(fd_, IPPROTO_IP, IP_ADD_MEMBERSHIP, &m, sizeof m) == 0);
  }
  ~Capture() { ::close(fd_); }
  Capture(const Capture&) = delete;
  Capture& operator=(const Capture&) = delete;
  // The next datagram, waiting up to 5 s.
  std::vector<std::byte> next() {
    pollfd p{fd_, POLLIN, 0};
    REQUIRE(::poll(&p, 1, 5000) == 1);
    std::vector<std::byte> d(65536);
    const auto n = ::recv(fd_, d.data(), d.size(), 0);
    REQUIRE(n > 0);
    d.resize(static_cast<std::size_t>(n));
    return d;
  }

 private:
  int fd_ = -1;
};

}  // namespace

// ---------------------------------------------------------------- key files

TEST_CASE("keyed: key files are written 0600 and read back, bad files are named with what is wrong",
          "[unit][keyed]") {
  TmpDir dir;
  const std::string file = (dir.path / "vehicle.key").string();
  GroupKeys k;
  k.keys = {generate_key(), generate_key()};
  k.encrypt = true;
  write_key_file(file, k, false);
  struct stat st {};
  REQUIRE(::stat(file.c_str(), &st) == 0);
  CHECK((st.st_mode & 0777) == 0600);
  const auto back = read_key_file(file);
  REQUIRE(back.keys.size() == 2);
  CHECK(back.keys[0].bytes == k.keys[0].bytes);
  CHECK(back.keys[1].bytes == k.keys[1].bytes);
  CHECK(back.keys[0].id == key_id(k.keys[0].bytes));
  CHECK(back.encrypt);
  CHECK(back.origin == file);

  SECTION("an existing file is replaced only with overwrite; a symbolic link never") {
    CHECK_THROWS_WITH(write_key_file(file, k, false), Catch::Contains("vehicle.key") && Catch::Contains("exists"));
    write_key_file(file, k, true);
    const std::string link = (dir.path / "link.key").string();
    REQUIRE(::symlink(file.c_str(), link.c_str()) == 0);
    CHECK_THROWS_WITH(write_key_file(link, k, true), Catch::Contains("symbolic link"));
  }
  SECTION("32 raw bytes are one key") {
    const std::string raw = (dir.path / "raw.key").string();
    {
      std::ofstream o(raw, std::ios::binary);
      o.write(reinterpret_cast<const char*>(k.keys[1].bytes.data()), 32);
    }
    ::chmod(raw.c_str(), 0600);
    const auto r = read_key_file(raw);
    REQUIRE(r.keys.size() == 1);
    CHECK(r.keys[0].bytes == k.keys[1].bytes);
    CHECK_FALSE(r.encrypt);
  }
  SECTION("readable by others: refused, naming the file and the fix") {
    ::chmod(file.c_str(), 0644);
    const auto e = key_error(file);
    CHECK_THAT(e, Catch::Contains(file) && Catch::Contains("chmod 600"));
  }
  SECTION("missing, not a key, three keys, a directory") {
    CHECK_THAT(key_error((dir.path / "none.key").string()), Catch::Contains("none.key") && Catch::Contains("cannot read"));
    const std::string junk = (dir.path / "junk.key").string();
    {
      std::ofstream o(junk);
      o << "# a comment\nnot a key at all\n";
    }
    ::chmod(junk.c_str(), 0600);
    CHECK_THAT(key_error(junk), Catch::Contains("line 2"));
    {
      std::ofstream o(junk);
      o << std::string(64, 'a') << "\n" << std::string(64, 'b') << "\n" << std::string(64, 'c') << "\n";
    }
    CHECK_THAT(key_error(junk), Catch::Contains("more than two keys"));
    {
      std::ofstream o(junk);
      o << "# nothing\n";
    }
    CHECK_THAT(key_error(junk), Catch::Contains("no key"));
    CHECK_THAT(key_error(dir.path.string()), Catch::Contains("not a key file"));
  }
}

// ---------------------------------------------------------------- envelope and replay window

TEST_CASE("keyed: the envelope round-trips authenticated and encrypted, any changed byte is refused",
          "[unit][keyed]") {
  const auto encrypt = GENERATE(false, true);
  INFO((encrypt ? "encrypted" : "authenticated"));
  const auto keys = keys_of({fixed_key(1)}, encrypt);
  lcmx::udpm::detail::Sealer sealer;
  const std::string inner = "LC02....CHANNEL\0payload bytes";
  std::vector<std::byte> buf(kEnvelopeOverhead + inner.size());
  std::memcpy(buf.data() + kEnvelopeHeaderSize, inner.data(), inner.size());
  const auto n = sealer.seal(*keys, buf.data(), inner.size());
  REQUIRE(n == buf.size());
  CHECK(std::memcmp(buf.data(), "LCXK", 4) == 0);
  const bool clear = std::memcmp(buf.data() + kEnvelopeHeaderSize, inner.data(), inner.size()) == 0;
  CHECK(clear == !encrypt);
  CHECK(libsodium_agrees(buf, inner, *keys));

  for (std::size_t at = 0; at < buf.size(); ++at) {  // every byte: header, body, tag
    auto copy = buf;
    copy[at] ^= std::byte{0x20};
    lcmx::udpm::detail::Opener fresh;
    const auto o = fresh.open(*keys, copy);
    INFO("byte " << at);
    REQUIRE(o.refused);
    CHECK(o.inner.empty());
  }
  lcmx::udpm::detail::Opener opener;
  auto copy = buf;
  const auto o = opener.open(*keys, copy);
  REQUIRE_FALSE(o.refused);
  CHECK(std::string(reinterpret_cast<const char*>(o.inner.data()), o.inner.size()) == inner);
  auto again = buf;
  CHECK(opener.open(*keys, again).refused == Refusal::replayed);
  auto other = buf;
  CHECK(lcmx::udpm::detail::Opener().open(*keys_of({fixed_key(2)}), other).refused == Refusal::unknown_key);
  std::vector<std::byte> lc02(40, std::byte{'L'});
  CHECK(opener.open(*keys, lc02).refused == Refusal::unkeyed);
  std::vector<std::byte> tiny(3);
  CHECK(opener.open(*keys, tiny).refused == Refusal::unkeyed);

  // The time stamp: a sender not heard yet is taken only within max_skew of our clock; a
  // known one by its counter alone.
  const auto now = static_cast<std::uint32_t>(std::time(nullptr));
  lcmx::udpm::detail::Opener late;
  auto old = buf;
  CHECK(late.open(*keys, old, 0, false, now + 3600, 60).refused == Refusal::stale);
  auto fine = buf;
  CHECK_FALSE(late.open(*keys, fine, 0, false, now + 30, 60).refused);
  std::vector<std::byte> next(kEnvelopeOverhead + inner.size());
  std::memcpy(next.data() + kEnvelopeHeaderSize, inner.data(), inner.size());
  sealer.seal(*keys, next.data(), inner.size());
  CHECK_FALSE(late.open(*keys, next, 0, false, now + 3600, 60).refused);  // known sender now
}

TEST_CASE("keyed: one-time keys made ahead give libsodium's bytes - for the counter expected, after a gap, "
          "reordered and after a key change", "[unit][keyed]") {
  using lcmx::udpm::detail::Opener;
  using lcmx::udpm::detail::Sealer;
  const auto encrypt = GENERATE(false, true);
  INFO((encrypt ? "encrypted" : "authenticated"));
  const auto a = keys_of({fixed_key(1)}, encrypt), b = keys_of({fixed_key(2)}, encrypt);
  const auto both = keys_of({fixed_key(1), fixed_key(2)}, encrypt);
  const std::string inner = std::string("LC02....CHANNEL\0", 16) + std::string(300, 'p');

  // The sender: made ahead or not, under the key it seals with or another one.
  Sealer sealer;
  std::vector<std::vector<std::byte>> sent;  // counters 1..
  sent.push_back(sealed(sealer, *a, inner));  // nothing made ahead
  sealer.prepare(*a);
  sent.push_back(sealed(sealer, *a, inner));  // made ahead, used
  sealer.prepare(*a);
  sent.push_back(sealed(sealer, *b, inner));  // made ahead under a, sealed under b
  sealer.prepare(*b);
  sent.push_back(sealed(sealer, *b, inner));
  sealer.prepare(*b);
  sent.push_back(sealed(sealer, *a, inner));  // back to a
  sealer.prepare(*a);
  sent.push_back(sealed(sealer, *a, inner));
  sent.push_back(sealed(sealer, *a, inner));
  sealer.prepare(*a);
  sent.push_back(sealed(sealer, *a, inner));
  const std::vector<const GroupKeys*> under = {a.get(), a.get(), b.get(), b.get(), a.get(), a.get(), a.get(), a.get()};
  for (std::size_t i = 0; i < sent.size(); ++i) {
    INFO("datagram " << i + 1);
    CHECK(libsodium_agrees(sent[i], inner, *under[i]));
  }

  // The receiver (holding both keys), making ahead after each: in order, across the key change,
  // after a gap (4 and 5 lost, then 5 late), reordered; a forgery with the counter it expects is
  // refused and leaves the next genuine datagram taken.
  Opener opener;
  const auto open = [&](std::size_t counter, bool prepare = true) {
    auto copy = sent[counter - 1];
    const auto o = opener.open(*both, copy);
    if (prepare) opener.prepare();
    INFO("counter " << counter);
    REQUIRE_FALSE(o.refused);
    CHECK(std::string_view(reinterpret_cast<const char*>(o.inner.data()), o.inner.size()) == inner);
  };
  open(1);
  open(2);
  open(3);  // made ahead under a, sealed under b
  open(6);  // made for 4
  open(5);  // made for 7
  auto forged = sent[6];
  forged[kEnvelopeHeaderSize + 20] ^= std::byte{1};
  CHECK(opener.open(*both, forged).refused == Refusal::bad_tag);
  open(7);
  open(8, false);
  auto again = sent[7];
  CHECK(opener.open(*both, again).refused == Refusal::replayed);
  open(4);  // late, within the window
}

TEST_CASE("keyed: the replay window takes each counter once, reordered within 960, not older", "[unit][keyed]") {
  lcmx::udpm::detail::ReplayWindow w;
  CHECK_FALSE(w.accept(0));
  CHECK(w.accept(2));
  CHECK_FALSE(w.accept(1));  // sent before the first one heard: refused (a late joiner)
  CHECK(w.accept(5));
  CHECK_FALSE(w.accept(5));
  CHECK(w.accept(3));
  CHECK(w.accept(4));
  CHECK(w.accept(1000));
  CHECK_FALSE(w.accept(3));  // older than the window now (1000 - 960 = 40)
  CHECK(w.accept(41));
  CHECK_FALSE(w.accept(41));
  CHECK(w.accept(999));
  CHECK(w.accept(100000));  // a long jump clears the whole bitmap
  CHECK(w.accept(99999));
  CHECK_FALSE(w.accept(1000));
  for (std::uint64_t c = 100001; c < 103000; ++c) REQUIRE(w.accept(c));
  for (std::uint64_t c = 102100; c < 103000; ++c) REQUIRE_FALSE(w.accept(c));
}

// ---------------------------------------------------------------- keyed Groups on lo

TEST_CASE("keyed: Groups with the key round-trip small and fragmented messages, authenticated and encrypted",
          "[integration][keyed]") {
  const auto encrypt = GENERATE(false, true);
  INFO((encrypt ? "encrypted" : "authenticated"));
  auto cfg = unique_config(encrypt ? "crypt" : "auth");
  cfg.keys = keys_of({fixed_key(7)}, encrypt);
  auto rx = Group::open(cfg);
  auto tx = Group::open(cfg);
  const std::string channel = "LCMX_KEYED";
  // Around the keyed LC02/LC03 boundary (the envelope must fit one datagram), 0 and 1 MB.
  const std::size_t boundary = kMaxDatagramSize - kEnvelopeOverhead - kShortHeaderSize - channel.size() - 1;
  const std::vector<std::size_t> sizes = {0, 1, 1024, 65400, boundary, boundary + 1, 65487, 300000, 1000000, 9};
  for (std::uint32_t i = 0; i < sizes.size(); ++i) tx.publish(channel, make_payload(i, sizes[i]));
  std::vector<std::pair<std::uint32_t, std::size_t>> got;
  bool ok = true;
  REQUIRE(poll_until(rx, [&](const Message& m) {
    ok = ok && m.channel == channel && payload_ok(m.data) && m.source == tx.local_source();
    got.emplace_back(m.sequence, m.data.size());
  }, [&] { return got.size() >= sizes.size(); }));
  CHECK(ok);
  for (std::uint32_t i = 0; i < sizes.size(); ++i) CHECK(got[i] == std::pair{i, sizes[i]});
  const auto& c = rx.counters();
  CHECK(c.unauthenticated_dropped == 0);
  CHECK(c.replays_dropped == 0);
  CHECK(c.malformed_dropped == 0);
  CHECK(c.incomplete_dropped == 0);
  // Every datagram still fits one IPv4 UDP datagram, envelope included.
  CHECK(c.bytes_received <= c.packets_received * kMaxDatagramSize);
  CHECK(rx.refusals().sources().empty());
}

TEST_CASE("keyed: unkeyed datagrams, another key and forged envelopes are refused and counted per source",
          "[integration][keyed]") {
  auto cfg = unique_config();
  cfg.keys = keys_of({fixed_key(1)});
  auto rx = Group::open(cfg);
  auto tx = Group::open(cfg);
  auto plain_cfg = cfg;
  plain_cfg.keys = nullptr;
  auto plain = Group::open(plain_cfg);  // an lcmx program without the key
  auto wrong_cfg = cfg;
  wrong_cfg.keys = keys_of({fixed_key(2)});
  auto wrong = Group::open(wrong_cfg);  // the wrong key
  RawSender raw(cfg);                   // stock LCM datagrams, and forged envelopes
  const auto payload = make_payload(1, 100);

  plain.publish("LCMX_KEYED", payload);
  plain.publish("LCMX_KEYED", make_payload(2, 200000));  // fragments
  wrong.publish("LCMX_KEYED", payload);
  raw.send(lc02(1, "LCMX_KEYED", payload));
  auto forged = lc02(2, "LCMX_KEYED", payload);
  const std::byte magic[4] = {std::byte{'L'}, std::byte{'C'}, std::byte{'X'}, std::byte{'K'}};
  forged.insert(forged.begin(), kEnvelopeHeaderSize, std::byte{0});
  std::memcpy(forged.data(), magic, 4);
  forged[4] = std::byte{kEnvelopeVersion};
  const auto id = cfg.keys->keys[0].id;  // the right key id, no valid tag
  for (int i = 0; i < 4; ++i) forged[8 + i] = std::byte(id >> (24 - 8 * i));
  forged.resize(forged.size() + kEnvelopeTagSize);
  raw.send(forged);
  tx.publish("LCMX_KEYED", payload);  // the one that counts, last

  std::vector<Source> from;
  REQUIRE(poll_until(rx, [&](const Message& m) { from.push_back(m.source); }, [&] { return !from.empty(); }));
  CHECK(from == std::vector<Source>{tx.local_source()});
  const auto& c = rx.counters();
  const auto plain_datagrams = 1 + datagram_count(10, 200000);
  CHECK(c.unauthenticated_dropped == plain_datagrams + 1 + 2);
  CHECK(c.messages_received == 1);
  CHECK(c.malformed_dropped == 0);  // refused before any parsing
  const auto sources = rx.refusals().sources();
  REQUIRE(sources.size() == 1);  // all from 127.0.0.1
  CHECK(sources[0].address_be == htonl(INADDR_LOOPBACK));
  CHECK(sources[0].count == plain_datagrams + 3);
  CHECK(sources[0].first == Refusal::unkeyed);
  CHECK(describe(sources[0]) ==
        "unauthenticated traffic from 127.0.0.1: wrong key or not lcmx (no key at all: stock LCM or lcmx without "
        "the group key)");
  CHECK(rx.refusals().take_new().size() == 1);
  CHECK(rx.refusals().take_new().empty());  // reported once
  // The wrong key's Group refuses the right key's datagrams in turn (unknown key).
  std::size_t heard = 0;
  poll_until(wrong, [&](const Message& m) { heard += m.source == wrong.local_source() ? 0 : 1; },
             [&] { return wrong.counters().unauthenticated_dropped >= 2; });
  CHECK(heard == 0);
  CHECK(wrong.refusals().sources().at(0).first != Refusal::replayed);
}

TEST_CASE("keyed: a captured valid datagram sent again is refused as a replay", "[integration][keyed]") {
  auto cfg = unique_config();
  cfg.keys = keys_of({fixed_key(3)}, true);
  auto rx = Group::open(cfg);
  Capture capture(cfg);
  auto tx = Group::open(cfg);
  tx.publish("LCMX_REPLAY", make_payload(1, 1024));
  const auto captured = capture.next();
  std::size_t got = 0;
  REQUIRE(poll_until(rx, [&](const Message&) { ++got; }, [&] { return got == 1; }));
  RawSender attacker(cfg);
  for (int i = 0; i < 3; ++i) attacker.send(captured);
  tx.publish("LCMX_REPLAY", make_payload(2, 1024));
  REQUIRE(poll_until(rx, [&](const Message&) { ++got; }, [&] { return got == 2; }));
  poll_until(rx, [&](const Message&) { ++got; }, [&] { return rx.counters().replays_dropped >= 3; }, 2000ms);
  CHECK(got == 2);
  CHECK(rx.counters().replays_dropped == 3);
  CHECK(rx.counters().unauthenticated_dropped == 0);
  const auto s = rx.refusals().sources();
  REQUIRE(s.size() == 1);
  CHECK(s[0].first == Refusal::replayed);

  // A Group's own datagram reflected back to it from another socket: its kernel filter drops
  // its own datagrams (receive_own = false, as the runtime opens its groups), so no window of
  // its own sender exists, and the reflection is refused all the same.
  auto self_cfg = cfg;
  self_cfg.receive_own = false;
  auto me = Group::open(self_cfg);
  Capture capture_me(cfg);
  me.publish("LCMX_REPLAY", make_payload(3, 100));
  const auto mine = capture_me.next();
  attacker.send(mine);
  std::size_t heard = 0;
  poll_until(me, [&](const Message&) { ++heard; }, [&] { return me.counters().replays_dropped >= 1; });
  CHECK(me.counters().replays_dropped == 1);
  CHECK(heard == 0);
}

TEST_CASE("keyed: a rotation window keeps traffic flowing with no loss", "[integration][keyed]") {
  // Three hosts' worth of Groups; the order of docs/keyed-groups.md "Rotation": every host
  // gets {A, B} (seals A), then {B, A} one by one (seals B), then {B}.
  const auto a = fixed_key(10), b = fixed_key(20);
  auto cfg = unique_config();
  cfg.keys = keys_of({a});
  std::vector<Group> hosts;
  for (int i = 0; i < 3; ++i) hosts.push_back(Group::open(cfg));
  std::vector<std::size_t> got(hosts.size(), 0);
  std::size_t sent = 0;
  auto round = [&](const char* step) {
    INFO(step);
    for (auto& h : hosts) h.publish("LCMX_ROTATE", make_payload(static_cast<std::uint32_t>(sent), 2000)), ++sent;
    for (std::size_t i = 0; i < hosts.size(); ++i)
      // Each host hears every datagram, its own included (multicast loop).
      REQUIRE(poll_until(hosts[i], [&](const Message&) { ++got[i]; }, [&] { return got[i] == sent; }));
  };
  round("all on A");
  for (auto& h : hosts) {
    h.set_keys(keys_of({a, b}));
    round("{A, B} rolled out host by host");
  }
  for (auto& h : hosts) {
    h.set_keys(keys_of({b, a}));
    round("{B, A}: some hosts seal B, others still A");
  }
  for (auto& h : hosts) {
    h.set_keys(keys_of({b}));
    round("{B} alone");
  }
  for (auto& h : hosts) {
    CHECK(h.counters().unauthenticated_dropped == 0);
    CHECK(h.counters().replays_dropped == 0);
  }
  // A host left on A alone is now refused by all.
  hosts[0].set_keys(keys_of({a}));
  hosts[0].publish("LCMX_ROTATE", make_payload(0, 10));
  CHECK(poll_until(hosts[1], [&](const Message&) { ++got[1]; },
                   [&] { return hosts[1].counters().unauthenticated_dropped == 1; }));
  CHECK(hosts[1].refusals().sources().at(0).first == Refusal::unknown_key);
}

TEST_CASE("keyed: stock liblcm ignores a keyed group's datagrams cleanly and is refused by it",
          "[integration][keyed][interop]") {
  Netns ns;
  EnterNetns in(ns);
  auto cfg = unique_config();
  const std::string url = "udpm://" + cfg.address + ":" + std::to_string(cfg.port) + "?ttl=0&recv_buf_size=4194304";
  cfg.keys = keys_of({fixed_key(5)});
  auto keyed = Group::open(cfg);
  auto plain_cfg = cfg;
  plain_cfg.keys = nullptr;
  auto plain = Group::open(plain_cfg);
  // liblcm's subscriber expects exactly one message: the unkeyed one sent after the keyed ones.
  Child sub({LCMX_UDPM_PEER, "sub", url, "LCMX_STOCK", "1", "15000"});
  REQUIRE(sub.read_line() == std::optional<std::string>("ready"));
  for (std::uint32_t i = 0; i < 5; ++i) keyed.publish("LCMX_STOCK", make_payload(i, i == 4 ? 200000 : 500));
  plain.publish("LCMX_STOCK", make_payload(77, 300));
  CHECK(sub.read_line() == std::optional<std::string>("msg LCMX_STOCK 77 300 ok"));
  CHECK(sub.read_line() == std::optional<std::string>("done 1"));
  CHECK(sub.wait() == 0);
  // And what liblcm sends on the keyed group is refused there.
  Child pub({LCMX_UDPM_PEER, "pub", url, "LCMX_STOCK", "3", "100"});
  CHECK(pub.wait() == 0);
  std::size_t heard = 0;
  poll_until(keyed, [&](const Message& m) { heard += m.source == keyed.local_source() ? 0 : 1; },
             [&] { return keyed.counters().unauthenticated_dropped >= 4; });
  CHECK(heard == 0);
  // plain's one, liblcm's three, and liblcm's self-test datagrams (LCM_SELF_TEST)
  CHECK(keyed.counters().unauthenticated_dropped >= 4);
}
