// The bytes of one outgoing message (a data message's JSON, a service response): parts in
// order, sent by one gathering write. A large part (an image's base64) is shared, not copied, by
// every payload that holds it: a struct and its image view, every client that gets them.
// Immutable once queued (shared_ptr<const Payload>); any thread.
#pragma once

#include <cstddef>
#include <memory>
#include <string>
#include <vector>

namespace lcmx::foxglove::detail {

struct Payload {
  std::vector<std::shared_ptr<const std::string>> parts;
  std::size_t size = 0;  // of all parts

  void add(std::shared_ptr<const std::string> part) {
    size += part->size();
    parts.push_back(std::move(part));
  }
  std::string joined() const {
    std::string s;
    s.reserve(size);
    for (const auto& p : parts) s += *p;
    return s;
  }
  // A payload of one part.
  static std::shared_ptr<const Payload> of(std::string text) {
    auto p = std::make_shared<Payload>();
    p->add(std::make_shared<const std::string>(std::move(text)));
    return p;
  }
};

}  // namespace lcmx::foxglove::detail
