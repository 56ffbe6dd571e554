// Publishes one message of its own type and receives it in the same process (intra path).
#include <unistd.h>

#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <mutex>
#include <string>
#include <vector>

#include "consumer_msgs/greeting_t.hpp"
#include "lcmx/core.hpp"
#include "lcmx/types/types.hpp"

int main() {
  try {
    auto rt = lcmx::Runtime::create();
    auto node = rt.create_node("consumer");
    const std::string channel = "CONSUMER_GREETING_" + std::to_string(::getpid());
    std::mutex mu;
    std::condition_variable cv;
    bool got = false;
    consumer_msgs::greeting_t received;
    auto sub = node.subscribe<consumer_msgs::greeting_t>(channel, [&](const consumer_msgs::greeting_t& m) {
      std::lock_guard lock(mu);
      received = m;
      got = true;
      cv.notify_all();
    });
    auto pub = node.advertise<consumer_msgs::greeting_t>(channel);
    if (!pub.wait_for_subscribers(1, std::chrono::seconds(5))) {
      std::fprintf(stderr, "consumer: subscriber not matched\n");
      return 1;
    }
    consumer_msgs::greeting_t m;
    m.id = 42;
    m.text = "hello from a consumer project";
    m.values = {1.5, 2.5, 3.5};
    m.n = static_cast<std::int32_t>(m.values.size());
    pub.publish(m);
    std::unique_lock lock(mu);
    if (!cv.wait_for(lock, std::chrono::seconds(5), [&] { return got; })) {
      std::fprintf(stderr, "consumer: message not received\n");
      return 1;
    }
    if (received.id != 42 || received.text != m.text || received.values != m.values) {
      std::fprintf(stderr, "consumer: message received but different\n");
      return 1;
    }
    // The same message decoded at run time from my.lcm (lcmx::types), without generated code.
    std::vector<std::uint8_t> bytes(static_cast<std::size_t>(m.getEncodedSize()));
    m.encode(bytes.data(), 0, static_cast<int>(bytes.size()));
    const auto types = lcmx::types::TypeRegistry::load({MY_LCM});
    const lcmx::types::Value tree = lcmx::types::decode(types, bytes.data(), bytes.size());
    if (lcmx::types::to_json(tree) !=
        R"({"id":42,"text":"hello from a consumer project","n":3,"values":[1.5,2.5,3.5]})") {
      std::fprintf(stderr, "consumer: lcmx::types decoded %s\n", lcmx::types::to_json(tree).c_str());
      return 1;
    }
    std::printf("consumer ok: %s (%s)\n", received.text.c_str(), consumer_msgs::greeting_t::getTypeName());
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "consumer: %s\n", e.what());
    return 1;
  }
}
