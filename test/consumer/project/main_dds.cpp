// lcmx::dds from an installed lcmx: a gateway config mapping the consumer's own type, read and
// validated (the type resolved from my.lcm), and the DDS type generated from my.lcm by
// lcmx_generate_dds_types() (idlc's descriptor, what a DDS program's topic is created with).
#include <cstdio>
#include <exception>
#include <string>

#include "lcmx/dds/config.hpp"
#include "my_dds_types.h"

int main() {
  try {
    const std::string text = std::string("name = \"consumer\"\ndomain = 7\ninterface = \"127.0.0.1\"\n") +
                             "types = [\"" + MY_LCM + "\"]\n\n[[map]]\nchannel = \"GREETING\"\n" +
                             "direction = \"both\"\nmode = \"typed\"\ntype = \"consumer_msgs.greeting_t\"\n";
    const auto cfg = lcmx::dds::parse_config(text, "consumer.toml");
    if (cfg.mappings.size() != 1 || cfg.mappings[0].lcm_type == nullptr || cfg.cyclone_xml().empty()) {
      std::printf("consumer dds: config not as written\n");
      return 1;
    }
    const dds_topic_descriptor_t& d = consumer_msgs_greeting_t_desc;
    if (d.m_typename == nullptr || std::string(d.m_typename) != "consumer_msgs::greeting_t") {
      std::printf("consumer dds: generated type is '%s'\n", d.m_typename ? d.m_typename : "(null)");
      return 1;
    }
    std::printf("consumer dds ok: mapping %s (%s), DDS type %s\n", cfg.mappings[0].channel.c_str(),
                cfg.mappings[0].type.c_str(), d.m_typename);
    return 0;
  } catch (const std::exception& e) {
    std::printf("consumer dds: %s\n", e.what());
    return 1;
  }
}
