// Config validation (every bad key gives an error naming the file and the key), defaults,
// channel choice, CURVE key files, and the control wire format against hostile input.
#include <catch2/catch.hpp>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <string>

#include "lcmx/bridge/config.hpp"
#include "lcmx/bridge/detail/wire.hpp"
#include "lcmx/test/skip.hpp"

using namespace lcmx::bridge;
namespace fs = std::filesystem;

namespace {

const char* kBase = R"(
name = "chipA"
listen = ["10.1.0.1"]
control_port = 7700
)";

const char* kPeer = R"(
[[peer]]
name = "chipB"
endpoints = [ { link = "pcie", address = "10.1.0.2" }, { link = "eth", address = "10.0.0.2" } ]
)";

// A temporary folder of this test, removed at the end.
struct TempDir {
  fs::path path;
  TempDir() {
    std::string t = (fs::temp_directory_path() / "lcmx_bridge_cfg_XXXXXX").string();
    REQUIRE(::mkdtemp(t.data()) != nullptr);
    path = t;
  }
  ~TempDir() {
    std::error_code ec;
    fs::remove_all(path, ec);
  }
};

std::string error_of(const std::string& text, const fs::path& file = "/etc/lcmx/test.toml") {
  try {
    parse_config(text, file);
  } catch (const ConfigError& e) {
    return e.what();
  }
  return "";
}

}  // namespace

TEST_CASE("the example config is valid and means what its comments say", "[bridge][config]") {
  const auto c = load_config(LCMX_BRIDGE_EXAMPLE);
  CHECK(c.name == "chipA");
  CHECK(c.listen == std::vector<std::string>{"10.1.0.1", "10.0.0.1"});
  CHECK(c.control_port == 7700);
  CHECK(c.carry == std::vector<std::string>{"MAP_*"});
  REQUIRE(c.channels.size() == 2);
  CHECK(c.channels[0].name == "control");
  CHECK(c.channels[0].priority == 1);
  CHECK(c.channels[0].hwm == 100);
  CHECK(c.channels[1].hwm == 4);
  CHECK(c.channels[0].max_keep == 16);
  CHECK(c.channels[1].max_keep == 2);
  CHECK(c.max_catalogue == 256);
  REQUIRE(c.peers.size() == 1);
  CHECK(c.peers[0].endpoints.size() == 2);
  CHECK(c.peers[0].endpoints[0].link == "pcie");
  CHECK_FALSE(c.security.curve);
  CHECK(c.channel_of("POSE") == 0u);
  CHECK(c.channel_of("CMD_STEER") == 0u);
  CHECK(c.channel_of("CAMERA") == 1u);
  CHECK(c.carried("MAP_TILES"));
  CHECK_FALSE(c.carried("CAMERA"));
}

TEST_CASE("defaults: one channel on control_port+1 for every topic", "[bridge][config]") {
  const auto c = parse_config(std::string(kBase) + kPeer, "x.toml");
  CHECK(c.heartbeat.count() == 100);
  CHECK(c.link_timeout.count() == 500);
  CHECK(c.failback_hold.count() == 1000);
  CHECK(c.status_period.count() == 1000);
  REQUIRE(c.channels.size() == 1);
  CHECK(c.channels[0].name == "default");
  CHECK(c.channels[0].port == 7701);
  CHECK(c.channels[0].hwm == 16);
  CHECK(c.channels[0].drop == DropPolicy::oldest);
  CHECK(c.channels[0].max_keep == 16);
  CHECK(c.max_catalogue == 256);
  CHECK(c.channel_of("ANYTHING") == 0u);
  CHECK(c.carry.empty());
}

TEST_CASE("first matching channel wins, and a topic may match none", "[bridge][config]") {
  const auto c = parse_config(std::string(kBase) + R"(
[[channel]]
name = "fast"
port = 7710
topics = ["POSE*"]
[[channel]]
name = "img"
port = 7711
drop = "newest"
topics = ["CAM*", "POSE_BIG"]
)",
                              "x.toml");
  CHECK(c.channel_of("POSE_BIG") == 0u);
  CHECK(c.channel_of("CAMERA") == 1u);
  CHECK(c.channels[1].drop == DropPolicy::newest);
  CHECK_FALSE(c.channel_of("LIDAR").has_value());
}

TEST_CASE("every bad key is an error naming the file and the key", "[bridge][config]") {
  struct Case {
    const char* what;
    std::string text;
    std::string expect;  // substring of the message, after "<file>: "
  };
  const std::string b = kBase;
  const std::vector<Case> cases = {
      {"toml syntax", "name = \"chipA\nlisten = [", "line "},
      {"unknown top-level key", b + "heartbeat = 100\n", "heartbeat: unknown key"},
      {"missing name", "listen = [\"10.0.0.1\"]\ncontrol_port = 7700\n", "name: missing (required)"},
      {"name type", "name = 3\nlisten = [\"10.0.0.1\"]\ncontrol_port = 7700\n", "name: must be a string"},
      {"name chars", "name = \"chip A\"\nlisten = [\"10.0.0.1\"]\ncontrol_port = 7700\n", "name: must be 1 to 32"},
      {"name too long", "name = \"" + std::string(33, 'a') + "\"\nlisten = [\"10.0.0.1\"]\ncontrol_port = 7700\n",
       "name: must be 1 to 32"},
      {"missing listen", "name = \"a\"\ncontrol_port = 7700\n", "listen: missing"},
      {"empty listen", "name = \"a\"\nlisten = []\ncontrol_port = 7700\n", "listen: must list at least one"},
      {"listen not ipv4", "name = \"a\"\nlisten = [\"chipA.local\"]\ncontrol_port = 7700\n", "listen[0]: not an IPv4"},
      {"listen element type", "name = \"a\"\nlisten = [10]\ncontrol_port = 7700\n", "listen[0]: must be a string"},
      {"listen duplicate", "name = \"a\"\nlisten = [\"10.0.0.1\", \"10.0.0.1\"]\ncontrol_port = 7700\n",
       "listen[1]: duplicate"},
      {"missing control_port", "name = \"a\"\nlisten = [\"10.0.0.1\"]\n", "control_port: missing"},
      {"control_port range", "name = \"a\"\nlisten = [\"10.0.0.1\"]\ncontrol_port = 70000\n",
       "control_port: must be an integer from 1 to 65535 (got 70000)"},
      {"control_port type", "name = \"a\"\nlisten = [\"10.0.0.1\"]\ncontrol_port = \"7700\"\n",
       "control_port: must be an integer"},
      {"carry type", b + "carry = \"MAP_*\"\n", "carry: must be an array of strings"},
      {"carry empty pattern", b + "carry = [\"\"]\n", "carry[0]: empty pattern"},
      {"heartbeat range", b + "heartbeat_ms = 0\n", "heartbeat_ms: must be an integer from 10"},
      {"link_timeout < 2 heartbeats", b + "heartbeat_ms = 100\nlink_timeout_ms = 150\n",
       "link_timeout_ms: must be at least twice heartbeat_ms"},
      {"failback_hold type", b + "failback_hold_ms = 1.5\n", "failback_hold_ms: must be an integer"},
      {"status_period range", b + "status_period_ms = 10\n", "status_period_ms: must be an integer from 50"},
      {"channel not a table array", b + "channel = 3\n", "channel: must be an array of tables"},
      {"channel unknown key", b + "[[channel]]\nname = \"c\"\nport = 7701\nhwn = 3\n", "channel[0].hwn: unknown key"},
      {"channel missing name", b + "[[channel]]\nport = 7701\n", "channel[0].name: missing"},
      {"channel missing port", b + "[[channel]]\nname = \"c\"\n", "channel[0].port: missing"},
      {"channel port = control_port", b + "[[channel]]\nname = \"c\"\nport = 7700\n",
       "channel[0].port: port 7700 is already used"},
      {"channel duplicate port", b + "[[channel]]\nname = \"c\"\nport = 7701\n[[channel]]\nname = \"d\"\nport = 7701\n",
       "channel[1].port: port 7701 is already used"},
      {"channel duplicate name", b + "[[channel]]\nname = \"c\"\nport = 7701\n[[channel]]\nname = \"c\"\nport = 7702\n",
       "channel[1].name: duplicate channel name"},
      {"channel priority range", b + "[[channel]]\nname = \"c\"\nport = 7701\npriority = 8\n",
       "channel[0].priority: must be an integer from 0 to 7 (got 8)"},
      {"channel hwm range", b + "[[channel]]\nname = \"c\"\nport = 7701\nhwm = 0\n",
       "channel[0].hwm: must be an integer from 1 to 1000000 (got 0)"},
      {"channel drop value", b + "[[channel]]\nname = \"c\"\nport = 7701\ndrop = \"old\"\n",
       "channel[0].drop: must be \"oldest\" or \"newest\" (got \"old\")"},
      {"channel topics empty", b + "[[channel]]\nname = \"c\"\nport = 7701\ntopics = []\n",
       "channel[0].topics: must list at least one pattern"},
      {"peer unknown key", b + "[[peer]]\nname = \"b\"\nendpoints = [{link = \"eth\", address = \"10.0.0.2\"}]\nkey = 1\n",
       "peer[0].key: unknown key"},
      {"peer missing name", b + "[[peer]]\nendpoints = [{link = \"eth\", address = \"10.0.0.2\"}]\n", "peer[0].name: missing"},
      {"peer own name", b + "[[peer]]\nname = \"chipA\"\nendpoints = [{link = \"eth\", address = \"10.0.0.2\"}]\n",
       "peer[0].name: is this bridge's own name"},
      {"peer duplicate", b + kPeer + kPeer, "peer[1].name: duplicate peer \"chipB\""},
      {"peer no endpoints", b + "[[peer]]\nname = \"b\"\nendpoints = []\n", "peer[0].endpoints: must list at least one"},
      {"peer missing endpoints", b + "[[peer]]\nname = \"b\"\n", "peer[0].endpoints: must list at least one"},
      {"endpoint unknown key", b + "[[peer]]\nname = \"b\"\nendpoints = [{link = \"eth\", addr = \"10.0.0.2\"}]\n",
       "peer[0].endpoints[0].addr: unknown key"},
      {"endpoint address", b + "[[peer]]\nname = \"b\"\nendpoints = [{link = \"eth\", address = \"10.0.0.256\"}]\n",
       "peer[0].endpoints[0].address: not an IPv4 address"},
      {"endpoint missing link", b + "[[peer]]\nname = \"b\"\nendpoints = [{address = \"10.0.0.2\"}]\n",
       "peer[0].endpoints[0].link: missing"},
      {"endpoint duplicate link",
       b + "[[peer]]\nname = \"b\"\nendpoints = [{link = \"eth\", address = \"10.0.0.2\"}, {link = \"eth\", address = \"10.1.0.2\"}]\n",
       "peer[0].endpoints[1].link: duplicate link"},
      {"endpoint not a table", b + "[[peer]]\nname = \"b\"\nendpoints = [\"10.0.0.2\"]\n",
       "peer[0].endpoints[0]: must be a table"},
      {"security type", b + "security = true\n", "security: must be a table"},
      {"security unknown key", b + "[security]\ncurve = false\nsecret = \"x\"\n", "security.secret: unknown key"},
      {"security curve type", b + "[security]\ncurve = \"yes\"\n", "security.curve: must be true or false"},
      {"curve without key files", b + "[security]\ncurve = true\n", "security.secret_key_file: missing (required)"},
      {"curve key file missing", b + "[security]\ncurve = true\nsecret_key_file = \"nope.key\"\npublic_key_file = \"nope.pub\"\n",
       "security.secret_key_file: /etc/lcmx/nope.key: cannot read"},
  };
  for (const auto& c : cases) {
    INFO(c.what << "\n--- config:\n" << c.text);
    const auto msg = error_of(c.text);
    INFO("error: " << msg);
    REQUIRE(!msg.empty());
    CHECK(msg.rfind("/etc/lcmx/test.toml: ", 0) == 0);
    CHECK(msg.find(c.expect) != std::string::npos);
  }
}

TEST_CASE("errors give the line of the bad value", "[bridge][config]") {
  const auto msg = error_of(std::string(kBase) + "\n\n[[channel]]\nname = \"c\"\nport = 7701\nhwm = -3\n");
  CHECK(msg.find("channel[0].hwm: must be an integer from 1 to 1000000 (got -3) (line 10)") != std::string::npos);
}

TEST_CASE("a missing config file or a directory is a clear error", "[bridge][config]") {
  try {
    load_config("/nonexistent/lcmx/bridge.toml");
    FAIL("no error");
  } catch (const ConfigError& e) {
    CHECK(std::string(e.what()).find("/nonexistent/lcmx/bridge.toml: cannot read") == 0);
  }
  try {
    load_config("/tmp");
    FAIL("no error");
  } catch (const ConfigError& e) {
    CHECK(std::string(e.what()) == "/tmp: is a directory, not a config file (TOML)");
  }
}

TEST_CASE("CURVE keys: keygen files, config with keys, wrong pairs and bad files", "[bridge][config][curve]") {
  if (!curve_available()) LCMX_SKIP("libzmq without CURVE");
  TempDir dir;
  const auto a = generate_key_pair(), b = generate_key_pair();
  CHECK(a.public_key.size() == 40);
  CHECK(a.secret_key.size() == 40);
  CHECK(a.public_key != b.public_key);
  write_key_pair(dir.path / "chipA", a);
  write_key_pair(dir.path / "chipB", b);
  struct stat st {};
  REQUIRE(::stat((dir.path / "chipA.key").c_str(), &st) == 0);
  CHECK((st.st_mode & 0777) == 0600);
  CHECK(read_key_file(dir.path / "chipA.key") == a.secret_key);
  CHECK(read_key_file(dir.path / "chipA.pub") == a.public_key);
  CHECK_THROWS_AS(write_key_pair(dir.path / "chipA", a), ConfigError);  // no silent overwrite
  write_key_pair(dir.path / "chipA", a, true);

  const std::string good = std::string(kBase) + kPeer + "public_key_file = \"chipB.pub\"\n" +
                           "[security]\ncurve = true\nsecret_key_file = \"chipA.key\"\npublic_key_file = \"chipA.pub\"\n";
  const auto c = parse_config(good, dir.path / "a.toml");  // relative to the config's folder
  CHECK(c.security.curve);
  CHECK(c.security.secret_key == a.secret_key);
  CHECK(c.peers[0].public_key == b.public_key);

  // A peer without its key file, a public key that is not the secret's, a corrupt key.
  CHECK(error_of(std::string(kBase) + kPeer + "[security]\ncurve = true\nsecret_key_file = \"chipA.key\"\n" +
                     "public_key_file = \"chipA.pub\"\n",
                 dir.path / "a.toml")
            .find("peer[0].public_key_file: missing (required)") != std::string::npos);
  CHECK(error_of(std::string(kBase) + kPeer + "public_key_file = \"chipB.pub\"\n" +
                     "[security]\ncurve = true\nsecret_key_file = \"chipA.key\"\npublic_key_file = \"chipB.pub\"\n",
                 dir.path / "a.toml")
            .find("security.public_key_file: does not hold the public key") != std::string::npos);
  {
    std::ofstream(dir.path / "bad.pub") << "# comment\nnot-a-key\n";
  }
  CHECK(error_of(std::string(kBase) + kPeer + "public_key_file = \"bad.pub\"\n" +
                     "[security]\ncurve = true\nsecret_key_file = \"chipA.key\"\npublic_key_file = \"chipA.pub\"\n",
                 dir.path / "a.toml")
            .find("peer[0].public_key_file: " + (dir.path / "bad.pub").string() + ": not a CURVE key") !=
        std::string::npos);
  // Without CURVE the key files are not needed (nor read).
  CHECK_NOTHROW(parse_config(std::string(kBase) + kPeer + "public_key_file = \"missing.pub\"\n", dir.path / "a.toml"));
}

TEST_CASE("control wire format: round trip, and hostile frames are rejected", "[bridge][wire]") {
  wire::Control c;
  c.from = "chipA";
  c.instance = 0x0123456789abcdefull;
  c.link = "pcie";
  c.t_ns = 42;
  c.control_port = 7700;
  c.channels = {{"control", 7701}, {"bulk", 7702}};
  c.has_demand = true;
  c.want = {"CAMERA", "POSE"};
  c.offer = {"MAP_1"};
  c.have = {"CAMERA_FRONT", "MAP_1"};
  c.types = {{"MAP_1", {static_cast<std::int64_t>(0x8c636d7864647362ull), "lcmx_examples.map_t"}}};
  const auto text = wire::encode(c);
  auto d = wire::decode(text);
  REQUIRE(d);
  CHECK(d->from == "chipA");
  CHECK(d->instance == c.instance);
  CHECK(d->channels == c.channels);
  CHECK(d->want == c.want);
  CHECK(d->offer == c.offer);
  CHECK(d->have == c.have);
  CHECK(d->types == c.types);  // a negative fingerprint (top bit set) too
  CHECK(text.find("type MAP_1 8c636d7864647362 lcmx_examples.map_t\n") != std::string::npos);
  CHECK(d->has_demand);
  // Type lines: topic, 16 hex digits, a name without spaces, inside the demand state.
  const std::string head = "LCMXB1 PING\nfrom a\ninstance 0000000000000001\nlink l\nt 1\n";
  const std::string demand = "control 7700\ndemand\n";
  CHECK(wire::decode(head + demand + "type T 0000000000000001 p.t\n"));
  CHECK_FALSE(wire::decode(head + "type T 0000000000000001 p.t\n"));                    // no demand
  CHECK_FALSE(wire::decode(head + demand + "type T 01 p.t\n"));                         // short fingerprint
  CHECK_FALSE(wire::decode(head + demand + "type T 000000000000000g p.t\n"));           // not hex
  CHECK_FALSE(wire::decode(head + demand + "type T 0000000000000001\n"));               // no name
  CHECK_FALSE(wire::decode(head + demand + "type T 0000000000000001 \n"));              // empty name
  CHECK_FALSE(wire::decode(head + demand + "type T 0000000000000001 " + std::string(256, 'n') + "\n"));

  CHECK_FALSE(wire::decode(""));
  CHECK_FALSE(wire::decode("LCMXB2 PING\n"));
  CHECK_FALSE(wire::decode("LCMXB1 PING\nfrom a\n"));                                  // fields missing
  CHECK_FALSE(wire::decode("LCMXB1 PONG\nfrom a\ninstance 0000000000000001\nlink l\nt x\n"));
  CHECK_FALSE(wire::decode(text + "want X\n" + "bogus 1\n"));                        // unknown key
  CHECK_FALSE(wire::decode(text + "want " + std::string(64, 'T') + "\n"));           // topic too long
  CHECK_FALSE(wire::decode("LCMXB1 PING\nfrom a\ninstance 1\nlink l\nt 1\n"));       // short instance
  CHECK_FALSE(wire::decode("LCMXB1 PING\nfrom a\ninstance 0000000000000001\nlink l\nt 1\nwant X\n"));  // no demand
  CHECK_FALSE(wire::decode(std::string(wire::kMaxControlFrame + 1, 'x')));
  // Truncations of a valid frame never crash, and what still decodes (a cut at the end of a
  // line, or inside a topic, which leaves a shorter valid one: ZeroMQ never delivers a cut
  // frame, so this is only the parser's robustness) says nothing the frame did not: the same
  // sender, instance, link and port, and every topic a prefix of one the frame named.
  auto subset = [](const auto& part, const auto& whole) {
    return std::all_of(part.begin(), part.end(), [&](const std::string& t) {
      return std::any_of(whole.begin(), whole.end(), [&](const std::string& w) { return w.rfind(t, 0) == 0; });
    });
  };
  std::size_t decoded = 0;
  for (std::size_t n = 0; n < text.size(); ++n) {
    const auto t = wire::decode(text.substr(0, n));
    if (!t) continue;
    ++decoded;
    INFO("cut at " << n);
    CHECK(t->from == "chipA");
    CHECK(t->instance == c.instance);
    CHECK(t->link == "pcie");
    if (t->has_demand) CHECK(t->control_port == 7700);  // else a heartbeat without the state: 0
    CHECK(subset(t->want, c.want));
    CHECK(subset(t->offer, c.offer));
    CHECK(subset(t->have, c.have));
    CHECK(t->types.size() <= c.types.size());
  }
  CHECK(decoded > 0);  // the frame is cut after whole lines too, and those decode

  // A heartbeat without the full state ("active" only) is small: the idle link stays quiet.
  wire::Control light;
  light.from = "chipA";
  light.instance = c.instance;
  light.link = "pcie";
  light.t_ns = 1'700'000'000'000'000'000;
  light.active = true;
  const auto light_text = wire::encode(light);
  CHECK(light_text.size() < 100);
  auto l = wire::decode(light_text);
  REQUIRE(l);
  CHECK(l->active);
  CHECK_FALSE(l->has_demand);
  CHECK(l->channels.empty());

  unsigned char h[wire::kDataHeader];
  wire::encode_header({0xfedcba9876543210ull, 77}, h);
  const auto back = wire::decode_header(h);
  CHECK(back.instance == 0xfedcba9876543210ull);
  CHECK(back.seq == 77u);
}

TEST_CASE("config values at their limits: clear errors, never a hang or undefined behaviour", "[bridge][config]") {
  const std::string b = kBase;
  auto message = [](const std::string& text) -> std::string {
    try {
      (void)parse_config(text, "limits.toml");
    } catch (const ConfigError& e) {
      return e.what();
    }
    return "(accepted)";
  };
  // Channels beyond kMaxChannels (each needs its own I/O thread bit in a 64-bit affinity mask).
  std::string chans = b;
  for (std::size_t i = 0; i <= kMaxChannels; ++i)
    chans += "[[channel]]\nname = \"c" + std::to_string(i) + "\"\nport = " + std::to_string(8000 + i) + "\n";
  CHECK(message(chans).find("limits.toml: channel: at most 32 channels (got 33)") != std::string::npos);
  // Peers beyond kMaxPeers (one message is queued for at most kMaxPeers peers).
  std::string peers = b;
  for (std::size_t i = 0; i <= kMaxPeers; ++i)
    peers += "[[peer]]\nname = \"p" + std::to_string(i) + "\"\nendpoints = [ { link = \"eth\", address = \"10.0.0." +
             std::to_string(i % 250 + 2) + "\" } ]\n";
  CHECK(message(peers).find("limits.toml: peer: at most 64 peers (got 65)") != std::string::npos);
  std::string eps = b + "[[peer]]\nname = \"p\"\nendpoints = [";
  for (std::size_t i = 0; i <= kMaxEndpoints; ++i)
    eps += (i ? ", " : "") + std::string("{ link = \"l") + std::to_string(i) + "\", address = \"10.0.0.2\" }";
  eps += "]\n";
  CHECK(message(eps).find("peer[0].endpoints: at most 8 endpoints (got 9)") != std::string::npos);
  // Exactly at the limits: accepted.
  std::string ok = b;
  for (std::size_t i = 0; i < kMaxChannels; ++i)
    ok += "[[channel]]\nname = \"c" + std::to_string(i) + "\"\nport = " + std::to_string(8000 + i) + "\n";
  CHECK(parse_config(ok, "limits.toml").channels.size() == kMaxChannels);
  // Ports and timeouts at the edges.
  CHECK(message("name = \"a\"\nlisten = [\"10.0.0.1\"]\ncontrol_port = 65536\n").find("control_port: must be an integer from 1 to 65535") != std::string::npos);
  CHECK(message("name = \"a\"\nlisten = [\"10.0.0.1\"]\ncontrol_port = 65535\n").find("no room for the default channel") != std::string::npos);
  CHECK(message(b + "heartbeat_ms = 9223372036854775807\n").find("heartbeat_ms: must be an integer from 10 to 60000") != std::string::npos);
  CHECK(message(b + "link_timeout_ms = 600001\n").find("link_timeout_ms: must be an integer") != std::string::npos);
  // toml++ 3.3.0 (Debian 12) asserts on these table headers in debug builds (found by
  // fuzz_bridge_config; marzer/tomlplusplus#301): lcmx's builds give a parse error.
  for (const char* text : {"[[[1]]]", "[[[a]]]", "[[[]]", "[[=", "[\r\n"})
    CHECK(message(text).rfind("limits.toml: line ", 0) == 0);
  // toml++ 3.3.0 reaches __builtin_unreachable() on a non-ASCII character where it scans a
  // bare token, a key or whitespace (found by fuzz_bridge_config): refused before toml++ sees
  // it, anywhere but in comment lines...
  CHECK(message(b + "carry = [\"A\"]\xc3\xa9\n") ==
        "limits.toml: line 5: a non-ASCII character (allowed only in comment lines, and nowhere in a file with a "
        "multi-line string)");
  CHECK(message(b + "\xc2\xa0heartbeat_ms = 100\n").find("line 5: a non-ASCII") != std::string::npos);
  CHECK(message(b + "x = \"\"\"\n\n\"\"\"\nl\xef\xbb\xb7n = 1\n").find("line 8: a non-ASCII") != std::string::npos);
  CHECK(message(b + std::string("nam = 3.o[\".\xc6\xb9\0\0009\n", 18)).find("line 5: a non-ASCII") != std::string::npos);
  CHECK(message(b + "carry = [\"CAF\xc3\x89_*\"]\n").find("line 5: a non-ASCII") != std::string::npos);
  CHECK(message(b + "heartbeat_ms = 100 # \xc2\xb5s\n").find("line 5: a non-ASCII") != std::string::npos);
  // A line starting with '#' inside a multi-line string is not a comment: toml++ reads on after
  // the closing delimiter (found by fuzz_bridge_config in CI). Any multi-line string delimiter
  // makes the whole file ASCII-only.
  CHECK(message(b + "s = \"\"\"\n# \"\"\"\xc3\xa9\n").find("line 6: a non-ASCII") != std::string::npos);
  CHECK(message(b + "s = \'\'\'\n# \'\'\'\xcc\xaa\n").find("line 6: a non-ASCII") != std::string::npos);
  CHECK(message(b + "# caf\xc3\xa9\ns = \'\'\'\n\'\'\'\n").find("line 5: a non-ASCII") != std::string::npos);
  // ...where any UTF-8 is fine.
  const auto utf8 = parse_config(b + "# caf\xc3\xa9 \xe2\x89\xa5 2\n  # \xc2\xb5s\ncarry = [\"CAF_*\"]\n", "limits.toml");
  CHECK(utf8.carry == std::vector<std::string>{"CAF_*"});
}

TEST_CASE("a key file that is a device or too large is refused at once", "[bridge][config][curve]") {
  // /dev/zero was read line by line without end (the bridge hung at start-up, growing).
  const auto zero = [] {
    try {
      (void)read_key_file("/dev/zero");
    } catch (const ConfigError& e) {
      return std::string(e.what());
    }
    return std::string("(accepted)");
  }();
  CHECK(zero.find("/dev/zero: not a key file") != std::string::npos);
  TempDir dir;
  const auto big = dir.path / "big.pub";
  std::ofstream(big) << "# " << std::string(kMaxKeyFileBytes, 'x') << "\n";
  CHECK_THROWS_WITH(read_key_file(big), Catch::Contains("not a key file"));
  CHECK_THROWS_WITH(read_key_file(dir.path), Catch::Contains("not a key file"));
}

TEST_CASE("control wire format: the demand state is whole or absent", "[bridge][wire]") {
  const std::string head = "LCMXB1 PING\nfrom a\ninstance 0000000000000001\nlink l\nt 1\nactive\n";
  // Found by fuzz_bridge_frame: "demand" without "control" decoded as control port 0 (a false
  // hello mismatch at the peer) and did not survive encode + decode.
  CHECK_FALSE(wire::decode(head + "demand\nwant X\n"));
  CHECK_FALSE(wire::decode(head + "control 7700\n"));                 // control without demand
  CHECK_FALSE(wire::decode(head + "channel c 7701\n"));               // channel without demand
  const auto ok = wire::decode(head + "control 7700\nchannel c 7701\ndemand\nwant X\n");
  REQUIRE(ok);
  CHECK(ok->control_port == 7700);
  CHECK(wire::decode(wire::encode(*ok)));
}

TEST_CASE("control wire format: the catalogue (have) belongs to the demand state and is bounded", "[bridge][wire]") {
  const std::string head = "LCMXB1 PING\nfrom a\ninstance 0000000000000001\nlink l\nt 1\nactive\n";
  const std::string demand = head + "control 7700\ndemand\n";
  CHECK_FALSE(wire::decode(head + "have X\n"));                        // have without demand
  CHECK_FALSE(wire::decode(demand + "have " + std::string(64, 'T') + "\n"));  // topic too long
  CHECK_FALSE(wire::decode(demand + "have\n"));                        // no topic
  CHECK_FALSE(wire::decode("LCMXB1 PONG\nfrom a\ninstance 0000000000000001\nlink l\nt 1\nhave X\n"));
  std::string full = demand;
  for (std::size_t i = 0; i < wire::kMaxCatalogue; ++i) full += "have T" + std::to_string(i) + "\n";
  const std::string over = full + "have T_ONE_MORE\n";
  const auto ok = wire::decode(full);
  REQUIRE(ok);
  CHECK(ok->have.size() == wire::kMaxCatalogue);
  CHECK(wire::encode(*ok).size() < 16 * 1024);  // a full catalogue of short names: a small frame
  CHECK_FALSE(wire::decode(over));  // more than kMaxCatalogue topics: malformed
  // A repeated topic is one topic (a set), not a way around the bound.
  const auto dup = wire::decode(demand + "have X\nhave X\n");
  REQUIRE(dup);
  CHECK(dup->have == std::set<std::string>{"X"});
}

TEST_CASE("control wire format: keep lines (keep last N of offered topics) belong to the demand state and are bounded",
          "[bridge][wire]") {
  const std::string head = "LCMXB1 PING\nfrom a\ninstance 0000000000000001\nlink l\nt 1\nactive\n";
  const std::string demand = head + "control 7700\ndemand\n";
  CHECK_FALSE(wire::decode(head + "keep X 3\n"));     // keep without demand
  CHECK_FALSE(wire::decode(demand + "keep X\n"));     // no count
  CHECK_FALSE(wire::decode(demand + "keep X -1\n"));  // not a count
  CHECK_FALSE(wire::decode(demand + "keep X 3x\n"));
  CHECK_FALSE(wire::decode(demand + "keep X " + std::to_string(wire::Control::kMaxKeep + 1) + "\n"));
  CHECK_FALSE(wire::decode(demand + "keep " + std::string(64, 'T') + " 3\n"));  // topic too long
  const auto ok = wire::decode(demand + "offer X\nkeep X 3\noffer Y\nkeep Y 1000\n");
  REQUIRE(ok);
  CHECK(ok->keep == std::map<std::string, std::uint32_t>{{"X", 3}, {"Y", 1000}});
  const auto back = wire::decode(wire::encode(*ok));
  REQUIRE(back);
  CHECK(back->keep == ok->keep);
  CHECK(back->offer == ok->offer);
  // The data header carries the keep too.
  unsigned char h[wire::kDataHeader];
  wire::encode_header({7, 8, 9}, h);
  const auto d = wire::decode_header(h);
  CHECK(d.instance == 7u);
  CHECK(d.seq == 8u);
  CHECK(d.keep == 9u);
}

TEST_CASE("what a peer may ask of this host is capped by its config: max_keep, max_catalogue", "[bridge][config]") {
  const std::string b = kBase;
  const auto c = parse_config(b + "max_catalogue = 10\n[[channel]]\nname = \"bulk\"\nport = 7702\nmax_keep = 2\n"
                                  "[[channel]]\nname = \"ctl\"\nport = 7703\nmax_keep = 1000\n" + kPeer,
                              "x.toml");
  CHECK(c.max_catalogue == 10u);
  CHECK(c.channels[0].max_keep == 2u);
  CHECK(c.channels[1].max_keep == 1000u);
  CHECK(parse_config(b + "max_catalogue = 0\n[[channel]]\nname = \"c\"\nport = 7702\nmax_keep = 0\n", "x.toml")
            .channels[0]
            .max_keep == 0u);
  CHECK(error_of(b + "max_catalogue = 1025\n").find("max_catalogue: must be an integer from 0 to 1024") !=
        std::string::npos);
  CHECK(error_of(b + "max_catalogue = -1\n").find("max_catalogue: must be an integer from 0 to 1024") !=
        std::string::npos);
  CHECK(error_of(b + "[[channel]]\nname = \"c\"\nport = 7702\nmax_keep = 1001\n")
            .find("channel[0].max_keep: must be an integer from 0 to 1000") != std::string::npos);
  CHECK(error_of(b + "[[channel]]\nname = \"c\"\nport = 7702\nmax_keep = \"all\"\n")
            .find("channel[0].max_keep: must be an integer") != std::string::npos);
}

TEST_CASE("an address names one host: a peer's address shared with another peer or this bridge is refused",
          "[bridge][config]") {
  const std::string b = kBase;
  const std::string peer_c = "[[peer]]\nname = \"chipC\"\nendpoints = [ { link = \"eth\", address = \"10.0.0.2\" } ]\n";
  const auto shared = error_of(b + kPeer + peer_c);
  INFO(shared);
  CHECK(shared.find("peer[1].endpoints[0].address: duplicate address 10.0.0.2 (already peer chipB)") !=
        std::string::npos);
  CHECK(shared.find("(line ") != std::string::npos);
  const auto own = error_of(b + "[[peer]]\nname = \"chipB\"\nendpoints = [ { link = \"eth\", address = \"10.1.0.1\" } ]\n");
  CHECK(own.find("peer[0].endpoints[0].address: duplicate address 10.1.0.1 (already this bridge's listen)") !=
        std::string::npos);
  const auto twice = error_of(b + "[[peer]]\nname = \"chipB\"\nendpoints = [ { link = \"eth\", address = \"10.0.0.2\" }, "
                                  "{ link = \"pcie\", address = \"10.0.0.2\" } ]\n");
  CHECK(twice.find("peer[0].endpoints[1].address: duplicate address 10.0.0.2 (already peer chipB)") !=
        std::string::npos);
}

TEST_CASE("key files: a secret key readable by others or owned by another user, a public key writable by others, "
          "are refused",
          "[bridge][config][curve]") {
  if (!curve_available()) LCMX_SKIP("libzmq without CURVE");
  TempDir dir;
  write_key_pair(dir.path / "chipA", generate_key_pair());
  write_key_pair(dir.path / "chipB", generate_key_pair());
  const std::string text = std::string(kBase) + kPeer + "public_key_file = \"chipB.pub\"\n" +
                           "[security]\ncurve = true\nsecret_key_file = \"chipA.key\"\npublic_key_file = \"chipA.pub\"\n";
  const auto file = dir.path / "a.toml";
  CHECK(parse_config(text, file).security.curve);
  const auto key = dir.path / "chipA.key", pub = dir.path / "chipB.pub";
  for (mode_t m : {0640, 0604, 0644, 0660}) {
    REQUIRE(::chmod(key.c_str(), m) == 0);
    const auto e = error_of(text, file);
    INFO("mode " << std::oct << m << ": " << e);
    CHECK(e.find("security.secret_key_file: " + key.string() + ": a secret key must be owned by this user") !=
          std::string::npos);
    CHECK(e.find("chmod 600") != std::string::npos);
  }
  REQUIRE(::chmod(key.c_str(), 0400) == 0);
  CHECK(parse_config(text, file).security.curve);  // read-only for its owner: fine
  REQUIRE(::chmod(key.c_str(), 0600) == 0);
  if (::geteuid() == 0) {  // root can give it away: a key owned by another user is refused too
    REQUIRE(::chown(key.c_str(), 12345, 12345) == 0);
    CHECK(error_of(text, file).find("a secret key must be owned by this user (uid 0)") != std::string::npos);
    REQUIRE(::chown(key.c_str(), 0, 0) == 0);
    REQUIRE(::chown(pub.c_str(), 12345, 12345) == 0);
    CHECK(error_of(text, file).find("peer[0].public_key_file: " + pub.string() + ": a public key must be owned") !=
          std::string::npos);
    REQUIRE(::chown(pub.c_str(), 0, 0) == 0);
  }
  for (mode_t m : {0664, 0646}) {
    REQUIRE(::chmod(pub.c_str(), m) == 0);
    CHECK(error_of(text, file).find("peer[0].public_key_file: " + pub.string() +
                                    ": a public key must be owned by this user or root and writable by nobody else") !=
          std::string::npos);
  }
  REQUIRE(::chmod(pub.c_str(), 0644) == 0);
  CHECK(parse_config(text, file).security.curve);
}

TEST_CASE("keygen never writes through a symbolic link, with --force neither", "[bridge][config][curve]") {
  if (!curve_available()) LCMX_SKIP("libzmq without CURVE");
  TempDir dir;
  const auto target = dir.path / "precious";
  std::ofstream(target) << "do not overwrite\n";
  fs::create_symlink(target, dir.path / "chipA.key");
  for (bool force : {false, true}) {
    INFO("force " << force);
    CHECK_THROWS_WITH(write_key_pair(dir.path / "chipA", generate_key_pair(), force),
                      Catch::Contains((dir.path / "chipA.key").string() + ": is a symbolic link: refused"));
  }
  std::ifstream in(target);
  std::string line;
  std::getline(in, line);
  CHECK(line == "do not overwrite");
  CHECK(fs::is_symlink(dir.path / "chipA.key"));
  // A link to nowhere (a file the attacker would have created) as well.
  fs::create_symlink(dir.path / "nowhere", dir.path / "chipB.pub");
  CHECK_THROWS_WITH(write_key_pair(dir.path / "chipB", generate_key_pair(), true),
                    Catch::Contains("chipB.pub: is a symbolic link: refused"));
  CHECK_FALSE(fs::exists(dir.path / "nowhere"));
  // --force replaces a regular file, keeping the modes; no temporary file is left behind.
  const auto k1 = generate_key_pair(), k2 = generate_key_pair();
  write_key_pair(dir.path / "chipC", k1);
  write_key_pair(dir.path / "chipC", k2, true);
  CHECK(read_key_file(dir.path / "chipC.key", KeyFile::secret) == k2.secret_key);
  CHECK(read_key_file(dir.path / "chipC.pub") == k2.public_key);
  struct stat st {};
  REQUIRE(::stat((dir.path / "chipC.key").c_str(), &st) == 0);
  CHECK((st.st_mode & 0777) == 0600);
  REQUIRE(::stat((dir.path / "chipC.pub").c_str(), &st) == 0);
  CHECK((st.st_mode & 0777) == 0644);
  int files = 0;
  for ([[maybe_unused]] const auto& e : fs::directory_iterator(dir.path)) ++files;
  CHECK(files == 5);  // precious, the links chipA.key and chipB.pub, chipC.key, chipC.pub
}

TEST_CASE("control wire format: a want line may carry the demand's age in ms (the start-up race), nothing else",
          "[bridge][wire]") {
  const std::string head = "LCMXB1 PING\nfrom a\ninstance 0000000000000001\nlink l\nt 1\nactive\n";
  const std::string demand = head + "control 7700\ndemand\n";
  const auto ok = wire::decode(demand + "want X 250\nwant Y\nwant Z " +
                               std::to_string(wire::Control::kMaxWantAgeMs) + "\n");
  REQUIRE(ok);
  CHECK(ok->want == std::set<std::string>{"X", "Y", "Z"});
  CHECK(ok->want_age_ms ==
        std::map<std::string, std::uint32_t>{{"X", 250}, {"Z", wire::Control::kMaxWantAgeMs}});  // Y: absent, 0
  const auto back = wire::decode(wire::encode(*ok));
  REQUIRE(back);
  CHECK(back->want == ok->want);
  CHECK(back->want_age_ms == ok->want_age_ms);
  CHECK_FALSE(wire::decode(demand + "want X 0\n"));  // 0 is written as no age: one spelling
  CHECK_FALSE(wire::decode(demand + "want X -5\n"));
  CHECK_FALSE(wire::decode(demand + "want X 12ms\n"));
  CHECK_FALSE(wire::decode(demand + "want X 1 2\n"));
  CHECK_FALSE(wire::decode(demand + "want X \n"));
  CHECK_FALSE(wire::decode(demand + "want X " + std::to_string(wire::Control::kMaxWantAgeMs + 1) + "\n"));
  CHECK_FALSE(wire::decode(demand + "offer X 250\n"));  // offers carry none
  // The encoder writes an age above the limit as the limit, and none for a topic not wanted.
  wire::Control c = *ok;
  c.want_age_ms["X"] = wire::Control::kMaxWantAgeMs + 1000;
  c.want_age_ms["NOT_WANTED"] = 5;
  const auto text = wire::encode(c);
  CHECK(text.find("want X " + std::to_string(wire::Control::kMaxWantAgeMs) + "\n") != std::string::npos);
  CHECK(text.find("NOT_WANTED") == std::string::npos);
  REQUIRE(wire::decode(text));
}

TEST_CASE("control wire format: want and offer lines are bounded", "[bridge][wire]") {
  std::string f = "LCMXB1 PING\nfrom a\ninstance 0000000000000001\nlink l\nt 1\ncontrol 7700\ndemand\n";
  for (std::size_t i = 0; i < wire::kMaxDemand; ++i) f += "want W" + std::to_string(i) + "\n";
  const auto d = wire::decode(f);
  REQUIRE(d);
  CHECK(d->want.size() == wire::kMaxDemand);
  CHECK_FALSE(wire::decode(f + "want ONE_MORE\n"));
  std::string o = "LCMXB1 PING\nfrom a\ninstance 0000000000000001\nlink l\nt 1\ncontrol 7700\ndemand\n";
  for (std::size_t i = 0; i <= wire::kMaxDemand; ++i) o += "offer O" + std::to_string(i) + "\n";
  CHECK_FALSE(wire::decode(o));
}

TEST_CASE("control wire format: any LCM channel name is one word, spelled one way", "[bridge][wire]") {
  // Names with a space, a tab, a newline, '%', DEL, an escape sequence and UTF-8.
  const std::vector<std::string> names = {"CAM FRONT", "a\tb", "x\ny", "100%", "%20", "d\x7f", "\x1b[2J",
                                          "kam\xc3\xa9ra", std::string(63, ' ')};
  for (const auto& n : names) {
    INFO(n);
    REQUIRE(wire::valid_topic(n));
    const auto w = wire::encode_topic(n);
    for (unsigned char c : w) CHECK((c > ' ' && c != 0x7f));  // one word of the text
    CHECK(wire::decode_topic(w) == n);
  }
  CHECK(wire::encode_topic("CAM FRONT") == "CAM%20FRONT");
  CHECK(wire::encode_topic("100%") == "100%25");
  CHECK(wire::encode_topic("CAMERA") == "CAMERA");  // names that need nothing stay as they were
  // One spelling per name: other escapes, lower-case hex, a cut escape, a bare '%' are refused.
  for (const char* w : {"%41", "%2a", "%2", "%", "a%zz", "%00"}) CHECK_FALSE(wire::decode_topic(w));
  CHECK_FALSE(wire::decode_topic(""));
  CHECK_FALSE(wire::decode_topic(std::string(64, 'T')));                  // 64 bytes
  CHECK_FALSE(wire::decode_topic(std::string(3 * 63 + 1, 'T')));
  CHECK(wire::decode_topic(wire::encode_topic(std::string(63, '%'))));    // 189 characters, 63 bytes
  CHECK_FALSE(wire::valid_topic(std::string("a\0b", 3)));                 // NUL: never a channel name
  CHECK_FALSE(wire::valid_topic(""));
  // In frames: every topic line, round trip.
  wire::Control c;
  c.from = "chipA";
  c.instance = 1;
  c.link = "pcie";
  c.t_ns = 1;
  c.has_demand = true;
  c.control_port = 7700;
  c.want = {"CAM FRONT", "100%"};
  c.offer = {"CAM FRONT"};
  c.have = {"CAM FRONT"};
  c.keep = {{"CAM FRONT", 3}};
  c.types = {{"CAM FRONT", {42, "lcmx_examples.image_t"}}};
  const auto text = wire::encode(c);
  CHECK(text.find("want CAM%20FRONT\n") != std::string::npos);
  CHECK(text.find("keep CAM%20FRONT 3\n") != std::string::npos);
  const auto d = wire::decode(text);
  REQUIRE(d);
  CHECK(d->want == c.want);
  CHECK(d->offer == c.offer);
  CHECK(d->have == c.have);
  CHECK(d->keep == c.keep);
  CHECK(d->types == c.types);
  const std::string head = "LCMXB1 PING\nfrom a\ninstance 0000000000000001\nlink l\nt 1\ncontrol 7700\ndemand\n";
  CHECK_FALSE(wire::decode(head + "want CAM FRONT\n"));  // a bare space: two words
  CHECK_FALSE(wire::decode(head + "have %41\n"));
}
