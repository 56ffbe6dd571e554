// The gateway: mappings (topic, writer, reader, lcmx endpoints), demand, loops, type checks and
// status. Contracts in lcmx/dds/gateway.hpp.
#include "lcmx/dds/gateway.hpp"

#include <unistd.h>

#include <spdlog/spdlog.h>

#include <atomic>
#include <condition_variable>
#include <cstring>
#include <map>
#include <mutex>
#include <set>
#include <thread>
#include <unordered_map>

#include "lcmx/core.hpp"
#include "lcmx/dds/entity.hpp"
#include "lcmx/dds/typed.hpp"
#include "lcmx_envelope.h"

namespace lcmx::dds {
namespace {

using namespace std::chrono_literals;
constexpr auto kTick = 20ms;

// Whether a QoS carries the gateways' USER_DATA.
bool is_gateway_qos(const dds_qos_t* qos) {
  void* value = nullptr;
  size_t size = 0;
  if (qos == nullptr || !dds_qget_userdata(qos, &value, &size)) return false;
  const bool yes = value != nullptr && size == std::strlen(kGatewayUserData) &&
                   std::memcmp(value, kGatewayUserData, size) == 0;
  dds_free(value);
  return yes;
}

void set_gateway_userdata(dds_qos_t* q) { dds_qset_userdata(q, kGatewayUserData, std::strlen(kGatewayUserData)); }

std::int64_t now_us() {
  return std::chrono::duration_cast<std::chrono::microseconds>(std::chrono::system_clock::now().time_since_epoch())
      .count();
}

}  // namespace

struct Mapping {
  MappingConfig cfg;
  std::unique_ptr<TypedType> typed;  // typed mode
  std::string dds_type;
  std::string lcm_type_name;         // "pkg.type_t" or ""
  std::int64_t fingerprint = 0;      // the mapping's type's, 0 if none
  Entity publisher, subscriber, topic, writer, reader;
  Subscriber<void> export_sub;
  RawPublisher import_pub;
  Gateway::Impl* gw = nullptr;

  std::atomic<std::uint64_t> exported{0}, exported_bytes{0}, export_drops{0};
  std::atomic<std::uint64_t> imported{0}, imported_bytes{0}, import_drops{0}, suppressed{0};
  std::atomic<int> dds_readers{0}, lcmx_subscribers{0}, dds_writers{0};

  mutable std::mutex err_mu;
  std::vector<std::string> errors;  // first 16 distinct
  std::set<std::string> error_keys;

  // Import listener only (Cyclone calls one reader's listener at a time).
  std::unordered_map<dds_instance_handle_t, bool> writer_is_gateway;
  // Control thread only.
  std::unordered_map<dds_instance_handle_t, bool> reader_is_gateway;

  // Records an error once per key (logged once, kept for the status).
  void error(const std::string& key, const std::string& text) {
    std::lock_guard lock(err_mu);
    if (!error_keys.insert(key).second) return;
    spdlog::warn("dds-gateway: {}", text);
    if (errors.size() < 16) errors.push_back(text);
  }
};

struct Gateway::Impl {
  Config cfg;
  std::optional<Runtime> runtime;
  std::optional<Node> node;
  Publisher<lcmx_msgs::dds_gateway_status_t> status_pub;
  Entity domain, participant, builtin_pubs, builtin_subs;
  std::vector<std::unique_ptr<Mapping>> maps;
  std::map<std::string, Mapping*> by_topic;

  std::mutex mu;
  std::condition_variable cv;
  bool stopping = false;
  std::thread control;
  std::size_t status_subscribers = 0;

  void setup_mapping(Mapping& m);
  void export_message(Mapping& m, const RawMessage& msg);
  static void on_data_available(dds_entity_t reader, void* arg);
  void import_samples(Mapping& m, dds_entity_t reader);
  void update_export_demand(Mapping& m);
  void update_import_demand(Mapping& m);
  void check_builtin(dds_entity_t reader, bool writers);
  void run_control();
  lcmx_msgs::dds_gateway_status_t status() const;
  void stop();
};

void Gateway::Impl::setup_mapping(Mapping& m) {
  const auto& c = m.cfg;
  if (c.lcm_type) {
    m.lcm_type_name = c.lcm_type->full_name();
    m.fingerprint = static_cast<std::int64_t>(c.lcm_type->fingerprint);
  }
  const dds_topic_descriptor_t* desc = &lcmx_dds_Envelope_desc;
  m.dds_type = lcmx_dds_Envelope_desc.m_typename;
  if (c.mode == Mode::typed) {
    m.typed = TypedType::create(*c.lcm_type, c.ros2);
    desc = m.typed->descriptor();
    m.dds_type = m.typed->dds_type_name();
  }
  m.topic = Entity(dds_create_topic(participant.get(), desc, c.topic.c_str(), nullptr, nullptr),
                   "map '" + c.channel + "': dds_create_topic '" + c.topic + "' (" + m.dds_type + ")");
  Qos part;
  if (!c.partition.empty()) dds_qset_partition1(part.get(), c.partition.c_str());
  Qos q;
  dds_qset_reliability(q.get(), c.reliability == Reliability::reliable ? DDS_RELIABILITY_RELIABLE
                                                                       : DDS_RELIABILITY_BEST_EFFORT,
                       DDS_MSECS(100));
  dds_qset_history(q.get(), DDS_HISTORY_KEEP_LAST, c.history);
  dds_qset_durability(q.get(), c.durability == Durability::transient_local ? DDS_DURABILITY_TRANSIENT_LOCAL
                                                                           : DDS_DURABILITY_VOLATILE);
  set_gateway_userdata(q.get());
  if (c.exports()) {
    m.publisher = Entity(dds_create_publisher(participant.get(), part.get(), nullptr), "dds_create_publisher");
    m.writer = Entity(dds_create_writer(m.publisher.get(), m.topic.get(), q.get(), nullptr),
                      "map '" + c.channel + "': dds_create_writer");
  }
  if (c.imports()) {
    m.subscriber = Entity(dds_create_subscriber(participant.get(), part.get(), nullptr), "dds_create_subscriber");
    // The import publisher exists all along: lcmx subscribers match it, which is the demand.
    if (!m.lcm_type_name.empty())
      m.import_pub = node->advertise_raw(c.channel, c.lcm_type->name, m.fingerprint);
    else
      m.import_pub = node->advertise_raw(c.channel);
  }
}

void Gateway::Impl::export_message(Mapping& m, const RawMessage& msg) {
  const auto bytes = msg.data;
  dds_return_t rc = DDS_RETCODE_OK;
  if (m.typed) {
    TypedType::Sample sample;
    try {
      sample = m.typed->from_lcm(bytes);
    } catch (const std::exception& e) {
      m.export_drops.fetch_add(1);
      m.error("export-decode", "map '" + m.cfg.channel + "': an lcmx message did not convert to " + m.dds_type +
                                   ": " + e.what());
      return;
    }
    rc = dds_write(m.writer.get(), sample.data());
  } else {
    lcmx_dds_Envelope e{};
    const auto fp = types::message_fingerprint(bytes.data(), bytes.size());
    e.channel = const_cast<char*>(m.cfg.channel.c_str());
    std::string type_name = m.lcm_type_name;
    if (type_name.empty() && fp)
      if (const auto* t = cfg.types->find(*fp)) type_name = t->full_name();
    e.type_name = const_cast<char*>(type_name.c_str());
    e.fingerprint = fp ? static_cast<std::int64_t>(*fp) : 0;
    e.payload._buffer = reinterpret_cast<std::uint8_t*>(const_cast<std::byte*>(bytes.data()));
    e.payload._length = e.payload._maximum = static_cast<std::uint32_t>(bytes.size());
    e.payload._release = false;
    rc = dds_write(m.writer.get(), &e);
  }
  if (rc < 0) {
    m.export_drops.fetch_add(1);
    m.error("export-write", "map '" + m.cfg.channel + "': dds_write: " + dds_strretcode(rc));
    return;
  }
  m.exported.fetch_add(1);
  m.exported_bytes.fetch_add(bytes.size());
}

void Gateway::Impl::on_data_available(dds_entity_t reader, void* arg) {
  auto* m = static_cast<Mapping*>(arg);
  m->gw->import_samples(*m, reader);
}

void Gateway::Impl::import_samples(Mapping& m, dds_entity_t reader) {
  constexpr int kBatch = 16;
  void* samples[kBatch] = {};
  dds_sample_info_t infos[kBatch];
  for (;;) {
    samples[0] = nullptr;  // loans
    const dds_return_t n = dds_take(reader, samples, infos, kBatch, kBatch);
    if (n <= 0) break;
    for (int i = 0; i < n; ++i) {
      if (!infos[i].valid_data) continue;
      // Never import what a gateway exported (loops, docs/dds.md).
      const auto h = infos[i].publication_handle;
      auto it = m.writer_is_gateway.find(h);
      if (it == m.writer_is_gateway.end()) {
        bool gw_writer = false;
        if (dds_builtintopic_endpoint_t* ep = dds_get_matched_publication_data(reader, h)) {
          gw_writer = is_gateway_qos(ep->qos);
          dds_builtintopic_free_endpoint(ep);
        }
        it = m.writer_is_gateway.emplace(h, gw_writer).first;
      }
      if (it->second) {
        m.suppressed.fetch_add(1);
        continue;
      }
      try {
        if (m.typed) {
          const auto lcm = m.typed->to_lcm(samples[i]);
          m.import_pub.publish(std::as_bytes(std::span(lcm)));
          m.imported_bytes.fetch_add(lcm.size());
        } else {
          const auto* e = static_cast<const lcmx_dds_Envelope*>(samples[i]);
          const std::span<const std::byte> payload(reinterpret_cast<const std::byte*>(e->payload._buffer),
                                                   e->payload._length);
          const auto fp = types::message_fingerprint(payload.data(), payload.size());
          if (!fp || (m.fingerprint != 0 && static_cast<std::int64_t>(*fp) != m.fingerprint)) {
            m.import_drops.fetch_add(1);
            m.error("import-fingerprint", "map '" + m.cfg.channel + "': an envelope's payload is not a " +
                                              m.lcm_type_name + " (" +
                                              (fp ? "fingerprint differs" : "shorter than a fingerprint") +
                                              ", envelope type '" + std::string(e->type_name ? e->type_name : "") +
                                              "'): dropped");
            continue;
          }
          m.import_pub.publish(payload);
          m.imported_bytes.fetch_add(payload.size());
        }
        m.imported.fetch_add(1);
      } catch (const std::exception& e) {
        m.import_drops.fetch_add(1);
        m.error("import", "map '" + m.cfg.channel + "': a DDS sample was not imported: " + e.what());
      }
    }
    dds_return_loan(reader, samples, n);
    if (n < kBatch) break;
  }
}

void Gateway::Impl::update_export_demand(Mapping& m) {
  dds_instance_handle_t handles[256];
  const dds_return_t n = dds_get_matched_subscriptions(m.writer.get(), handles, 256);
  int native = 0;
  std::unordered_map<dds_instance_handle_t, bool> current;  // the cache keeps matched readers only
  for (dds_return_t i = 0; i < n && i < 256; ++i) {
    bool gw_reader = false;
    if (auto it = m.reader_is_gateway.find(handles[i]); it != m.reader_is_gateway.end()) {
      gw_reader = it->second;
    } else {
      dds_builtintopic_endpoint_t* ep = dds_get_matched_subscription_data(m.writer.get(), handles[i]);
      if (!ep) continue;  // gone meanwhile
      gw_reader = is_gateway_qos(ep->qos);
      dds_builtintopic_free_endpoint(ep);
    }
    current.emplace(handles[i], gw_reader);
    if (!gw_reader) ++native;
  }
  m.reader_is_gateway = std::move(current);
  m.dds_readers.store(native);
  if (native > 0 && !m.export_sub) {
    SubscriberOptions so;
    so.from_dds_gateways = false;  // never send back what a gateway imported
    so.queue_depth = static_cast<std::size_t>(m.cfg.history);
    auto cb = [this, mp = &m](const RawMessage& msg) { export_message(*mp, msg); };
    if (!m.lcm_type_name.empty())
      m.export_sub = node->subscribe_raw(m.cfg.channel, m.cfg.lcm_type->name, m.fingerprint, cb, so);
    else
      m.export_sub = node->subscribe_raw(m.cfg.channel, cb, so);
    spdlog::info("dds-gateway: '{}' -> DDS topic '{}': {} DDS reader(s), exporting", m.cfg.channel, m.cfg.topic,
                 native);
  } else if (native == 0 && m.export_sub) {
    m.export_sub.reset();
    spdlog::info("dds-gateway: '{}' -> DDS topic '{}': no DDS reader, export stopped", m.cfg.channel, m.cfg.topic);
  }
}

void Gateway::Impl::update_import_demand(Mapping& m) {
  const auto subs = m.import_pub.subscriber_count();
  m.lcmx_subscribers.store(static_cast<int>(subs));
  dds_subscription_matched_status_t sm{};
  m.dds_writers.store(m.reader && dds_get_subscription_matched_status(m.reader.get(), &sm) == DDS_RETCODE_OK
                          ? static_cast<int>(sm.current_count)
                          : 0);
  if (subs > 0 && !m.reader) {
    Qos q;
    dds_qset_reliability(q.get(), m.cfg.reliability == Reliability::reliable ? DDS_RELIABILITY_RELIABLE
                                                                             : DDS_RELIABILITY_BEST_EFFORT,
                         DDS_MSECS(100));
    dds_qset_history(q.get(), DDS_HISTORY_KEEP_LAST, m.cfg.history);
    dds_qset_durability(q.get(), m.cfg.durability == Durability::transient_local ? DDS_DURABILITY_TRANSIENT_LOCAL
                                                                                 : DDS_DURABILITY_VOLATILE);
    dds_qset_ignorelocal(q.get(), DDS_IGNORELOCAL_PARTICIPANT);
    set_gateway_userdata(q.get());
    dds_listener_t* l = dds_create_listener(&m);
    dds_lset_data_available(l, &Impl::on_data_available);
    const dds_entity_t r = dds_create_reader(m.subscriber.get(), m.topic.get(), q.get(), l);
    dds_delete_listener(l);
    if (r < 0) {
      m.error("reader", "map '" + m.cfg.channel + "': dds_create_reader: " + dds_strretcode(r));
      return;
    }
    m.reader = Entity(r, "dds_create_reader");
    spdlog::info("dds-gateway: DDS topic '{}' -> '{}': {} lcmx subscriber(s), importing", m.cfg.topic, m.cfg.channel,
                 subs);
  } else if (subs == 0 && m.reader) {
    m.reader.reset();  // waits for a running listener
    spdlog::info("dds-gateway: DDS topic '{}' -> '{}': no lcmx subscriber, import stopped", m.cfg.topic,
                 m.cfg.channel);
  }
}

// DCPSPublication / DCPSSubscription: reports DDS endpoints on a mapped topic with another type.
void Gateway::Impl::check_builtin(dds_entity_t reader, bool writers) {
  constexpr int kBatch = 16;
  void* samples[kBatch] = {};
  dds_sample_info_t infos[kBatch];
  for (;;) {
    samples[0] = nullptr;
    const dds_return_t n = dds_take(reader, samples, infos, kBatch, kBatch);
    if (n <= 0) break;
    for (int i = 0; i < n; ++i) {
      if (!infos[i].valid_data || infos[i].instance_state != DDS_IST_ALIVE) continue;
      const auto* ep = static_cast<const dds_builtintopic_endpoint_t*>(samples[i]);
      if (!ep->topic_name || !ep->type_name) continue;
      auto it = by_topic.find(ep->topic_name);
      if (it == by_topic.end()) continue;
      Mapping& m = *it->second;
      if (m.dds_type == ep->type_name) continue;
      char key[64];
      std::snprintf(key, sizeof key, "type:%d:%016llx", writers ? 1 : 0,
                    static_cast<unsigned long long>(infos[i].instance_handle));
      m.error(key, std::string("map '") + m.cfg.channel + "': a DDS " + (writers ? "writer" : "reader") +
                       " on topic '" + ep->topic_name + "' has type " + ep->type_name + ", this mapping's is " +
                       m.dds_type + ": not matched, ignored");
    }
    dds_return_loan(reader, samples, n);
    if (n < kBatch) break;
  }
}

void Gateway::Impl::run_control() {
  auto next_status = std::chrono::steady_clock::now();
  std::unique_lock lock(mu);
  while (!stopping) {
    lock.unlock();
    try {
      for (auto& m : maps) {
        if (m->cfg.exports()) update_export_demand(*m);
        if (m->cfg.imports()) update_import_demand(*m);
      }
      check_builtin(builtin_pubs.get(), true);
      check_builtin(builtin_subs.get(), false);
      const auto now = std::chrono::steady_clock::now();
      const auto watchers = status_pub.subscriber_count();
      if (now >= next_status || watchers > status_subscribers) {
        if (watchers > 0) status_pub.publish(status());
        next_status = now + cfg.status_period;
      }
      status_subscribers = watchers;
    } catch (const std::exception& e) {
      spdlog::error("dds-gateway: control: {}", e.what());
    }
    lock.lock();
    cv.wait_for(lock, kTick, [&] { return stopping; });
  }
}

lcmx_msgs::dds_gateway_status_t Gateway::Impl::status() const {
  lcmx_msgs::dds_gateway_status_t s{};
  s.timestamp_us = now_us();
  s.name = cfg.name;
  s.host_id = runtime ? static_cast<std::int64_t>(runtime->host_id()) : 0;
  s.pid = static_cast<std::int32_t>(::getpid());
  s.domain = static_cast<std::int32_t>(cfg.domain);
  s.partition = cfg.partition;
  for (const auto& m : maps) {
    lcmx_msgs::dds_mapping_status_t ms{};
    ms.channel = m->cfg.channel;
    ms.topic = m->cfg.topic;
    ms.dds_type = m->dds_type;
    ms.mode = to_string(m->cfg.mode);
    ms.direction = to_string(m->cfg.direction);
    ms.dds_readers = m->dds_readers.load();
    ms.lcmx_subscribers = m->lcmx_subscribers.load();
    ms.dds_writers = m->dds_writers.load();
    ms.exporting = m->cfg.exports() && ms.dds_readers > 0 ? 1 : 0;
    ms.importing = m->cfg.imports() && ms.lcmx_subscribers > 0 ? 1 : 0;
    ms.exported = static_cast<std::int64_t>(m->exported.load());
    ms.exported_bytes = static_cast<std::int64_t>(m->exported_bytes.load());
    ms.export_drops = static_cast<std::int64_t>(m->export_drops.load());
    ms.imported = static_cast<std::int64_t>(m->imported.load());
    ms.imported_bytes = static_cast<std::int64_t>(m->imported_bytes.load());
    ms.import_drops = static_cast<std::int64_t>(m->import_drops.load());
    ms.suppressed = static_cast<std::int64_t>(m->suppressed.load());
    {
      std::lock_guard lock(m->err_mu);
      ms.errors = m->errors;
    }
    ms.num_errors = static_cast<std::int32_t>(ms.errors.size());
    s.mappings.push_back(std::move(ms));
  }
  s.num_mappings = static_cast<std::int32_t>(s.mappings.size());
  return s;
}

void Gateway::Impl::stop() {
  {
    std::lock_guard lock(mu);
    if (stopping && !control.joinable()) return;
    stopping = true;
  }
  cv.notify_all();
  if (control.joinable()) control.join();
  for (auto& m : maps) m->export_sub.reset();  // waits for a running export callback
  for (auto& m : maps) m->reader.reset();      // waits for a running import listener
  maps.clear();                                // writers, topics, lcmx publishers
  builtin_pubs.reset();
  builtin_subs.reset();
  participant.reset();
  domain.reset();
  status_pub = {};
  node.reset();
  runtime.reset();
}

Gateway::Gateway(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
Gateway::Gateway(Gateway&&) noexcept = default;
Gateway& Gateway::operator=(Gateway&& o) noexcept {
  if (this != &o) {
    stop();
    impl_ = std::move(o.impl_);
  }
  return *this;
}
Gateway::~Gateway() { stop(); }

void Gateway::stop() {
  if (impl_) impl_->stop();
}

lcmx_msgs::dds_gateway_status_t Gateway::status() const { return impl_->status(); }

Gateway Gateway::start(Config cfg, RuntimeOptions options) {
  auto impl = std::make_unique<Impl>();
  Impl& g = *impl;
  g.cfg = std::move(cfg);
  options.dds_gateway = true;
  g.runtime.emplace(Runtime::create(options));
  NodeOptions no;
  // sched_getaffinity is per thread: the executor's thread inherits this one's mask.
  no.executor.slice = g.cfg.slice ? *g.cfg.slice : default_slice();
  spdlog::debug("dds-gateway {}: executor slice {} us{}", g.cfg.name, no.executor.slice.count(),
                g.cfg.slice ? "" : " (slice_us not set: by the CPUs this process may use)");
  if (g.cfg.spin.count() > 0) {
    no.executor.wait = WaitStrategy::adaptive;
    no.executor.spin = g.cfg.spin;
  }
  g.node.emplace(g.runtime->create_node("dds_gateway_" + g.cfg.name, no));
  g.status_pub = g.node->advertise<lcmx_msgs::dds_gateway_status_t>(kStatusChannel);

  const std::string xml = g.cfg.cyclone_xml();
  if (!xml.empty())
    g.domain = Entity(dds_create_domain(g.cfg.domain, xml.c_str()),
                      "DDS domain " + std::to_string(g.cfg.domain) + " (interface " + g.cfg.interface + ")");
  Qos pq;
  set_gateway_userdata(pq.get());
  g.participant = Entity(dds_create_participant(g.cfg.domain, pq.get(), nullptr),
                         "dds_create_participant (domain " + std::to_string(g.cfg.domain) + ")");
  g.builtin_pubs = Entity(dds_create_reader(g.participant.get(), DDS_BUILTIN_TOPIC_DCPSPUBLICATION, nullptr, nullptr),
                          "reader of DCPSPublication");
  g.builtin_subs = Entity(dds_create_reader(g.participant.get(), DDS_BUILTIN_TOPIC_DCPSSUBSCRIPTION, nullptr, nullptr),
                          "reader of DCPSSubscription");
  for (const auto& mc : g.cfg.mappings) {
    auto m = std::make_unique<Mapping>();
    m->cfg = mc;
    m->gw = &g;
    try {
      g.setup_mapping(*m);
    } catch (const types::Error& e) {
      throw ConfigError(g.cfg.file.string() + ": map '" + mc.channel + "': " + e.what());
    }
    g.by_topic[mc.topic] = m.get();
    g.maps.push_back(std::move(m));
  }
  g.control = std::thread([&g] { g.run_control(); });
  return Gateway(std::move(impl));
}

}  // namespace lcmx::dds
