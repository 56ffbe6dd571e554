// CURVE authentication: the ZAP handler thread (which peers may connect, as whom) and the
// User-Id check of every received message. The decision itself: security.hpp.
#include "engine.hpp"
#include "security.hpp"

#include <zmq.h>

#include <span>

#include <spdlog/spdlog.h>

namespace lcmx::bridge {

using namespace std::chrono_literals;

security::ZapAnswer security::zap_decide(std::string_view mechanism, std::span<const std::byte> client_key,
                                         const std::vector<PeerConfig>& peers) {
  ZapAnswer a{"400", "not a configured peer", "", ""};
  if (mechanism != "CURVE" || client_key.size() != 32) return a;
  char z85[41] = {};
  ::zmq_z85_encode(z85, reinterpret_cast<const std::uint8_t*>(client_key.data()), 32);
  a.key = z85;
  for (const auto& p : peers)
    if (!p.public_key.empty() && p.public_key == a.key) {
      a.status = "200", a.text = "OK", a.user = p.name;
      break;
    }
  return a;
}

// With CURVE, the authenticated user id (the peer name the ZAP handler assigned) must match.
bool Bridge::Impl::authentic(zmq::message_t& m, const std::string& claimed) {
  if (!cfg.security.curve) return true;
  try {
    const char* uid = m.gets("User-Id");
    return uid && claimed == uid;
  } catch (const zmq::error_t&) {
    return false;
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
        mechanism, std::span<const std::byte>(static_cast<const std::byte*>(req[6].data()), req[6].size()), cfg.peers);
    const std::string &status = answer.status, &text = answer.text, &user = answer.user;
    if (refused_log.size() > 1024) refused_log.clear();  // one limiter per address: bounded
    if (status != "200" && refused_log[address].allow()) {
      if (mechanism == "CURVE")
        spdlog::warn("bridge {}: refused a CURVE connection from {}: public key {} is not a configured peer's",
                     cfg.name, address, answer.key);
      else
        spdlog::warn("bridge {}: refused a connection from {}: mechanism {} (CURVE required)", cfg.name, address,
                     mechanism);
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
