// lcmx_bridge_attacker: what a hostile machine (or a compromised peer) can send to a Message
// Bridge, for the attack tests in bridge_test.cpp (issue 34). It speaks the bridges' wire format
// (lcmx/bridge/detail/wire.hpp) with plain ZeroMQ sockets, and every loop is bounded by a count.
//
//   lcmx_bridge_attacker ping --to ADDR --port P --as NAME [--link L] [--count N] [--interval-ms I]
//                             [--have N --prefix X]
//       A DEALER with routing id NAME/L/<random> (as a bridge's control DEALER) sends N pings "from NAME" (a fresh instance, the demand
//       state with no want line, and N catalogue topics X0000, X0001, ...), one every I ms.
//   lcmx_bridge_attacker data --to ADDR --port P --as NAME --topic T [--count N] [--interval-ms I]
//                             [--keep K] [--size S] [--id ID]
//       A DEALER with routing id NAME (what a bridge's data DEALER used before issue 34; now
//       NAME/<random>: both name NAME) sends N data messages on T: lcmx_examples::bench_t of S
//       bytes whose data starts with ID (what lcmx_test_peer's sub counts in "sources"), with
//       the header's keep K.
//   lcmx_bridge_attacker peer --name NAME --listen ADDR --to ADDR [--port P] [--link L]
//                             [--have N --prefix X] [--seconds S]
//       A fake bridge NAME: answers pings on ADDR:P (so the target sees it up) and sends its
//       own pings with the demand state and N catalogue topics every 100 ms, for S seconds
//       (or until "quit" on stdin).
// Prints "READY" once its sockets are set up, "PONGS <n>" (pongs received) or "SENT <n>" (data
// messages ZeroMQ took) and "DONE" at the end.
// Exit 0, or 2 on bad arguments.
#include <poll.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <iostream>
#include <random>
#include <string>
#include <thread>
#include <zmq.hpp>

#include <CLI/CLI.hpp>

#include "lcmx/bridge/detail/wire.hpp"
#include "lcmx_examples/bench_t.hpp"

namespace {

namespace wire = lcmx::bridge::wire;
using Clock = std::chrono::steady_clock;

struct Args {
  std::string to, as, link = "eth", topic, id = "EVIL", prefix = "ATK_", listen;
  int port = 7700, count = 1, interval_ms = 20, have = 0, size = 70000, seconds = 10;
  std::uint64_t keep = 0;
};

std::uint64_t fresh_instance() {
  std::random_device rd;
  return (std::uint64_t{rd()} << 32) | rd() | 1u;
}

wire::Control demand_ping(const Args& a, const std::string& from, std::uint64_t instance) {
  wire::Control c;
  c.kind = wire::Control::Kind::ping;
  c.from = from;
  c.instance = instance;
  c.link = a.link;
  c.t_ns = Clock::now().time_since_epoch().count();
  c.active = true;
  c.has_demand = true;
  c.control_port = 7700;
  c.channels = {{"default", 7701}};
  char name[64];
  for (int i = 0; i < a.have && i < static_cast<int>(wire::kMaxCatalogue); ++i) {
    std::snprintf(name, sizeof name, "%s%04d", a.prefix.c_str(), i);
    c.have.insert(name);
  }
  return c;
}

int drain_pongs(zmq::socket_t& s) {
  int pongs = 0;
  for (int i = 0; i < 10000; ++i) {  // bounded
    zmq::message_t m;
    if (!s.recv(m, zmq::recv_flags::dontwait)) break;
    const auto c = wire::decode(m.to_string_view());
    if (c && c->kind == wire::Control::Kind::pong) ++pongs;
  }
  return pongs;
}

std::unique_ptr<zmq::socket_t> dealer(zmq::context_t& ctx, const std::string& routing_id, const std::string& to,
                                      int port) {
  auto s = std::make_unique<zmq::socket_t>(ctx, zmq::socket_type::dealer);
  s->set(zmq::sockopt::linger, 2000);  // what was queued is flushed before exit
  s->set(zmq::sockopt::routing_id, routing_id);
  s->connect("tcp://" + to + ":" + std::to_string(port));
  return s;
}

// A control DEALER's routing id as a bridge makes it: "<name>/<link>/<16 hex>".
std::string control_id(const Args& a) {
  char r[20];
  std::snprintf(r, sizeof r, "%016llx", static_cast<unsigned long long>(fresh_instance()));
  return a.as + "/" + a.link + "/" + r;
}

int do_ping(const Args& a) {
  zmq::context_t ctx;
  auto s = dealer(ctx, control_id(a), a.to, a.port);
  std::cout << "READY" << std::endl;
  const std::uint64_t instance = fresh_instance();
  int pongs = 0;
  for (int i = 0; i < a.count; ++i) {
    const std::string text = wire::encode(demand_ping(a, a.as, instance));
    (void)s->send(zmq::buffer(text), zmq::send_flags::dontwait);
    std::this_thread::sleep_for(std::chrono::milliseconds(a.interval_ms));  // the attack's pace
    pongs += drain_pongs(*s);
  }
  std::cout << "PONGS " << pongs << "\nDONE" << std::endl;
  return 0;
}

int do_data(const Args& a) {
  zmq::context_t ctx;
  auto s = dealer(ctx, a.as, a.to, a.port);
  std::cout << "READY" << std::endl;
  lcmx_examples::bench_t m{};
  m.size = std::max(a.size, 8);
  m.data.resize(static_cast<std::size_t>(m.size));
  const std::uint64_t instance = fresh_instance();
  int sent = 0;
  for (int k = 0; k < a.count; ++k) {
    m.seq = k;
    for (std::size_t i = 8; i < m.data.size(); ++i)
      m.data[i] = static_cast<std::uint8_t>((i * 131u + static_cast<std::uint64_t>(k) * 7u) & 0xffu);
    for (std::size_t i = 0; i < 8; ++i) m.data[i] = i < a.id.size() ? static_cast<std::uint8_t>(a.id[i]) : 0;
    std::string payload(static_cast<std::size_t>(m.getEncodedSize()), '\0');
    m.encode(payload.data(), 0, static_cast<int>(payload.size()));
    unsigned char hdr[wire::kDataHeader];
    wire::encode_header({instance, static_cast<std::uint64_t>(k) + 1, a.keep}, hdr);
    // Never blocks: a DEALER whose connection was refused has no peer to send to.
    if (s->send(zmq::buffer(a.topic), zmq::send_flags::sndmore | zmq::send_flags::dontwait)) {
      s->send(zmq::buffer(hdr, sizeof hdr), zmq::send_flags::sndmore);
      s->send(zmq::buffer(payload), zmq::send_flags::none);
      ++sent;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(a.interval_ms));  // the attack's pace
  }
  std::cout << "SENT " << sent << "\nDONE" << std::endl;
  return 0;
}

int do_peer(const Args& a) {
  zmq::context_t ctx;
  zmq::socket_t router(ctx, zmq::socket_type::router);
  router.set(zmq::sockopt::linger, 0);
  router.bind("tcp://" + a.listen + ":" + std::to_string(a.port));
  auto out = dealer(ctx, control_id(a), a.to, a.port);
  out->set(zmq::sockopt::linger, 0);
  std::cout << "READY" << std::endl;
  const std::uint64_t instance = fresh_instance();
  const auto end = Clock::now() + std::chrono::seconds(a.seconds);
  auto next_ping = Clock::now();
  int pongs = 0;
  while (Clock::now() < end) {
    zmq::pollitem_t items[] = {{router.handle(), 0, ZMQ_POLLIN, 0}, {nullptr, 0, ZMQ_POLLIN, 0}};
    zmq::poll(items, 2, std::chrono::milliseconds(50));
    if (items[1].revents & ZMQ_POLLIN) {
      std::string line;
      if (!std::getline(std::cin, line) || line == "quit") break;
    }
    for (int i = 0; i < 1000 && (items[0].revents & ZMQ_POLLIN); ++i) {  // answer pings
      zmq::message_t id, body;
      if (!router.recv(id, zmq::recv_flags::dontwait)) break;
      if (!id.more() || !router.recv(body, zmq::recv_flags::none)) continue;
      auto c = wire::decode(body.to_string_view());
      if (!c || c->kind != wire::Control::Kind::ping) continue;
      wire::Control pong;
      pong.kind = wire::Control::Kind::pong;
      pong.from = a.as;
      pong.instance = instance;
      pong.link = c->link;
      pong.t_ns = c->t_ns;
      const std::string text = wire::encode(pong);
      router.send(id, zmq::send_flags::sndmore | zmq::send_flags::dontwait);
      router.send(zmq::buffer(text), zmq::send_flags::dontwait);
    }
    if (Clock::now() >= next_ping) {
      const std::string text = wire::encode(demand_ping(a, a.as, instance));
      (void)out->send(zmq::buffer(text), zmq::send_flags::dontwait);
      next_ping += std::chrono::milliseconds(100);
    }
    pongs += drain_pongs(*out);
  }
  std::cout << "PONGS " << pongs << "\nDONE" << std::endl;
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"lcmx_bridge_attacker: hostile input for a Message Bridge (tests only)"};
  app.require_subcommand(1);
  Args a;
  auto* ping = app.add_subcommand("ping", "pings in another bridge's name");
  auto* data = app.add_subcommand("data", "data messages in another bridge's name");
  auto* peer = app.add_subcommand("peer", "a fake bridge that answers pings and sends a catalogue");
  for (auto* c : {ping, data, peer}) {
    c->add_option("--to", a.to, "the target bridge's address")->required();
    c->add_option("--port", a.port, "the target's port (control or channel)");
    c->add_option("--link", a.link, "link name in pings and routing ids");
    c->add_option("--have", a.have, "catalogue topics per ping")->check(CLI::Range(0, 1024));
    c->add_option("--prefix", a.prefix, "catalogue topic prefix");
  }
  for (auto* c : {ping, data}) {
    c->add_option("--as", a.as, "the bridge name (and routing id) claimed")->required();
    c->add_option("--count", a.count, "messages to send")->check(CLI::Range(1, 100000));
    c->add_option("--interval-ms", a.interval_ms, "pause between messages")->check(CLI::Range(0, 10000));
  }
  data->add_option("--topic", a.topic)->required();
  data->add_option("--keep", a.keep, "the data header's keep");
  data->add_option("--size", a.size, "bench_t data bytes")->check(CLI::Range(8, 16 << 20));
  data->add_option("--id", a.id, "the first 8 data bytes");
  peer->add_option("--name", a.as, "this fake bridge's name")->required();
  peer->add_option("--listen", a.listen, "address to answer pings on")->required();
  peer->add_option("--seconds", a.seconds, "how long it runs at most")->check(CLI::Range(1, 120));
  CLI11_PARSE(app, argc, argv);
  try {
    if (ping->parsed()) return do_ping(a);
    if (data->parsed()) return do_data(a);
    return do_peer(a);
  } catch (const std::exception& e) {
    std::cout << "FATAL " << e.what() << std::endl;
    return 1;
  }
}
