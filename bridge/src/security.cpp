// Who may connect, with or without CURVE: the ZAP handler thread (which peers may connect, from
// where, as whom) and the User-Id check of every received message. The decision: security.hpp.
#include "engine.hpp"
#include "security.hpp"

#include <zmq.h>

#include <span>

#include <spdlog/spdlog.h>

namespace lcmx::bridge {

using namespace std::chrono_literals;

security::ZapAnswer security::zap_decide(std::string_view mechanism, std::span<const std::byte> client_key,
                                         std::string_view address, bool curve, const std::vector<PeerConfig>& peers) {
  ZapAnswer a{"400", "not a configured peer", "", "", ""};
  const PeerConfig* by_address = nullptr;
  for (const auto& p : peers)
    for (const auto& e : p.endpoints)
      if (e.address == address) by_address = &p;
  const std::string addr(address);
  if (!curve) {
    if (mechanism != "NULL") {
      a.reason = "mechanism " + std::string(mechanism) + " (this bridge runs without CURVE)";
    } else if (!by_address) {
      a.reason = "not an address of a configured peer";
    } else {
      a.status = "200", a.text = "OK", a.user = by_address->name;
    }
    return a;
  }
  if (mechanism != "CURVE" || client_key.size() != 32) {
    a.reason = "mechanism " + std::string(mechanism) + " (CURVE required)";
    return a;
  }
  char z85[41] = {};
  ::zmq_z85_encode(z85, reinterpret_cast<const std::uint8_t*>(client_key.data()), 32);
  a.key = z85;
  const PeerConfig* by_key = nullptr;
  for (const auto& p : peers)
    if (!p.public_key.empty() && p.public_key == a.key) by_key = &p;
  if (!by_key) {
    a.reason = "public key " + a.key + " is not a configured peer's";
  } else if (by_key != by_address) {
    a.reason = "the key is " + by_key->name + "'s, but " + addr + " is not one of " + by_key->name + "'s addresses";
  } else {
    a.status = "200", a.text = "OK", a.user = by_key->name;
  }
  return a;
}

// The authenticated User-Id (the peer name the ZAP handler assigned to the connection, with or
// without CURVE) must be the name the message claims.
bool Bridge::Impl::authentic(zmq::message_t& m, const std::string& claimed) {
  try {
    const char* uid = m.gets("User-Id");
    return uid && claimed == uid;
  } catch (const zmq::error_t&) {
    return false;
  }
}

std::string Bridge::Impl::user_of(zmq::message_t& m) {
  try {
    const char* uid = m.gets("User-Id");
    return uid ? printable(uid) : std::string("?");
  } catch (const zmq::error_t&) {
    return "?";
  }
}

void Bridge::Impl::zap_loop() {
  std::map<std::string, RateLimit> refused_log;
  while (!stopping.load()) {
    zmq::pollitem_t item{zap->handle(), 0, ZMQ_POLLIN, 0};
    try {
      if (zmq::poll(&item, 1, std::chrono::milliseconds(100)) <= 0) continue;
    } catch (const zmq::error_t&) {
      continue;
    }
    std::vector<zmq::message_t> req;
    for (;;) {
      zmq::message_t m;
      if (!zap->recv(m, zmq::recv_flags::dontwait)) break;
      const bool more = m.more();
      req.push_back(std::move(m));
      if (!more) break;
    }
    while (req.size() < 7) req.emplace_back();  // malformed: still answered (REP must reply)
    const std::string version = req[0].to_string(), request_id = req[1].to_string(),
                      address = req[3].to_string(), mechanism = req[5].to_string();
    const auto answer = security::zap_decide(
        mechanism, std::span<const std::byte>(static_cast<const std::byte*>(req[6].data()), req[6].size()), address,
        cfg.security.curve, cfg.peers);
    const std::string &status = answer.status, &text = answer.text, &user = answer.user;
    if (refused_log.size() > 1024) refused_log.clear();  // one limiter per address: bounded
    if (status != "200") {
      refused.fetch_add(1, std::memory_order_relaxed);
      if (refused_log[address].allow())
        spdlog::warn("bridge {}: refused a {}connection from {}: {}", cfg.name, cfg.security.curve ? "CURVE " : "",
                     printable(address), answer.reason);
    }
    try {
      zap->send(zmq::buffer(version), zmq::send_flags::sndmore);
      zap->send(zmq::buffer(request_id), zmq::send_flags::sndmore);
      zap->send(zmq::buffer(status), zmq::send_flags::sndmore);
      zap->send(zmq::buffer(text), zmq::send_flags::sndmore);
      zap->send(zmq::buffer(user), zmq::send_flags::sndmore);
      zap->send(zmq::message_t(), zmq::send_flags::none);
    } catch (const zmq::error_t& e) {
      spdlog::error("bridge {}: ZAP reply failed: {}", cfg.name, e.what());
    }
  }
}

}  // namespace lcmx::bridge
