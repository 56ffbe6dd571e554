#include <spdlog/spdlog.h>

#include <cstring>

#include "internal.hpp"

namespace lcmx::detail {

PublisherImpl::PublisherImpl(std::shared_ptr<NodeImpl> n, std::string channel,
                             const TypeInfo& t, PublisherOptions o)
    : node(std::move(n)), id(node->runtime->new_endpoint_id()), type(t), options(o),
      channel_(std::move(channel)), mirrored_(node->runtime->mirrored(channel_)) {
  if (options.max_message_size == 0)
    throw Error(Errc::invalid_argument, "publisher '" + channel_ + "': max_message_size is 0");
  if (options.history > PublisherOptions::kMaxHistory)
    throw Error(Errc::invalid_argument, "publisher '" + channel_ + "': history " +
                                            std::to_string(options.history) + " exceeds " +
                                            std::to_string(PublisherOptions::kMaxHistory));
  shm::WriterOptions w;
  // Keep last N: the ring holds the kept messages for late shm subscribers (Reader backlog)
  // and carries them into each larger generation.
  w.slot_count = std::max<std::uint32_t>(options.shm_slots, options.history + 1);
  w.keep = options.history;
  w.initial_slot_size = std::min(options.shm_initial_slot_size, options.max_message_size);
  w.max_message_size = options.max_message_size;
  w.unique_base = true;  // shm_base_prefix + endpoint id: one runtime per process, ids never reused
  try {
    writer_.emplace(shm::Writer::create(node->runtime->shm_base_prefix + std::to_string(id), w));
    // The first lease, at least 2 s: a peer's match reaches us within a beacon exchange, which
    // a loaded machine can stretch past a short lease.
    startup_until_ = std::chrono::steady_clock::now() +
                     std::max<std::chrono::steady_clock::duration>(node->runtime->options.lease, std::chrono::seconds(2));
    writer_->set_hot_slot(false);  // the start-up window: the ring keeps recent messages
    announced_segment_ = writer_->segment_name();
    large_ = node->runtime->class_of(channel_) == TopicClass::large;
  } catch (const shm::Error& e) {
    throw Error(shm::Errc::invalid_argument == e.code() ? Errc::invalid_argument : Errc::transport,
                "publisher '" + channel_ + "': " + e.what());
  }
}

PublisherImpl::~PublisherImpl() { node->runtime->remove_publisher(this); }

std::string PublisherImpl::segment_name() const {
  std::lock_guard lock(publish_mu);
  return writer_->segment_name();
}

std::shared_ptr<const PublisherImpl::Targets> PublisherImpl::targets() const {
  std::lock_guard lock(intra_mu);
  return intra_;
}

void PublisherImpl::check_size(std::size_t size) const {
  if (size > options.max_message_size)
    throw Error(Errc::message_too_large,
                "publish on '" + channel_ + "': message of " + std::to_string(size) +
                    " bytes exceeds max_message_size " + std::to_string(options.max_message_size));
}

void PublisherImpl::deliver_intra(const Targets& t, std::shared_ptr<const void> object) {
  // A raw publisher's object is its Bytes copy (make_bytes): the items point into it.
  std::span<const std::byte> bytes;
  if (type.carries_bytes()) bytes = *std::static_pointer_cast<const Bytes>(object);
  for (const auto& target : t) push_intra(*target.sub, IntraItem{object, &type, target.stats, bytes});
}

// A large topic that a bridge of this host carries goes to other hosts through the bridges,
// except to subscribers not yet matched with their host's bridge republisher: while the
// bridges set up (they serve and offer a topic a few heartbeats after a subscriber appears;
// a topic may turn large before), those still get it over UDP, so the switch loses nothing.
// Messages still on their way through the bridges when a subscriber matches the republisher
// reach it a second time (docs/bridge.md "From UDP to the bridges without a loss").
bool PublisherImpl::wants_vehicle(std::size_t size) {
  const auto& rt = *node->runtime;
  if (!rt.vehicle_group) return false;
  if (large_.load() && rt.bridge_on_host()) return unbridged_udp_subscribers_.load() > 0;
  if (udp_subscribers_.load() > 0 || rt.options.vehicle_publish == VehiclePublish::always) return true;
  if (!in_startup()) return false;
  // The start-up window: small messages whoever listens (a subscriber of another host may
  // have matched us before we heard of it) until this process has heard the whole vehicle
  // (then every such subscriber is known and matched: udp_subscribers_ says; docs/discovery.md
  // "Complete"); larger ones, fragmented, once a subscriber of another host that takes them is
  // known, matched with us or not yet (a service's reply: its client matched the reply
  // publisher from the probe's answer and calls at once).
  if (unbridged_elsewhere_.load() > 0) return true;
  return size <= rt.options.udp_limit && !rt.vehicle_complete();
}

bool PublisherImpl::in_startup() {
  if (!startup_) return false;
  if (std::chrono::steady_clock::now() < startup_until_) return true;
  startup_ = false;
  writer_->set_hot_slot(true);
  return false;
}

// unbridged_elsewhere_ counts every subscriber that unbridged_udp_subscribers_ counts (and those
// not matched with this publisher yet): it alone decides.
bool PublisherImpl::bridged_only() const {
  return large_.load() && node->runtime->bridge_on_host() && unbridged_elsewhere_.load() == 0;
}

bool PublisherImpl::wants_udp(std::size_t size) {
  return wants_vehicle(size) || mirrors(size) || local_udp_subscribers_.load() > 0;
}

// The mirror takes small messages (<= udp_limit), judged message by message: a channel whose
// images turned it large still mirrors its small messages. A larger one is not mirrored
// (stock LCM programs on this host do not get it), logged once per publisher. publish_mu held.
bool PublisherImpl::mirrors(std::size_t size) {
  if (!mirrored_) return false;
  const std::size_t limit = node->runtime->options.udp_limit;
  if (size <= limit) return true;
  if (!warned_mirror_size_) {
    warned_mirror_size_ = true;
    spdlog::warn("lcmx: topic '{}': a {}-byte message is over udp_limit ({}): the mirror sends only "
                 "smaller ones, so stock LCM programs on this host do not get it (logged once)",
                 channel_, size, limit);
  }
  return false;
}

void PublisherImpl::mark_large() {
  if (large_.exchange(true)) return;
  spdlog::info("lcmx: topic '{}' is now large (carried by this host's Message Bridge)", channel_);
}

// Classifies by size: an automatic topic whose message exceeds udp_limit becomes large for
// good (announced at once). publish_mu held.
void PublisherImpl::note_size(std::size_t size) {
  const auto& rt = *node->runtime;
  if (size <= rt.options.udp_limit || large_.load()) return;
  if (rt.class_of(channel_) != TopicClass::automatic) return;
  large_.store(true);
  spdlog::info("lcmx: topic '{}' is now large ({} bytes > udp_limit {})", channel_, size,
               rt.options.udp_limit);
  node->runtime->changed();
}

// Sends an encoding over LCM UDP: on the vehicle group when a subscriber on another host
// wants it (or vehicle_publish = always), and on the host-local group for the mirror (small
// topics only; where the kernel routes the group, as stock LCM sends, so every stock
// receiver on this host hears it). A network fault (link or interface down) does not fail the publish: the
// local paths already delivered; the message is counted lost on UDP and logged (at most
// once per 5 s per publisher), and sending resumes when the network is back.
// publish_mu held.
PublisherImpl::UdpSent PublisherImpl::send_udp(std::span<const std::byte> encoded) {
  auto& rt = *node->runtime;
  UdpSent sent;
  auto send = [&](udpm::Group& group, const char* which) -> std::optional<std::uint32_t> {
    try {
      if (&group == rt.local_group.get()) return group.publish_routed(channel_, encoded);
      return group.publish(channel_, encoded);
    } catch (const udpm::Error& e) {
      if (e.code() != udpm::Error::Code::system) throw Error(Errc::transport, e.what());
      ++udp_send_failures_;
      const auto now = std::chrono::steady_clock::now();
      if (now - last_udp_failure_log_ > std::chrono::seconds(5)) {
        last_udp_failure_log_ = now;
        spdlog::warn("lcmx: topic '{}': cannot send on the {} group ({} lost so far): {}", channel_,
                     which, udp_send_failures_, e.what());
      }
      return std::nullopt;
    }
  };
  if (wants_vehicle(encoded.size())) {
    if (large_.load() && !rt.bridge_on_host() && !warned_large_udp_) {
      warned_large_udp_ = true;
      spdlog::warn("lcmx: topic '{}' is large and no Message Bridge runs on this host: sending it "
                   "to other hosts as UDP fragments (start `lcmx bridge` on every host)",
                   channel_);
    } else if (large_.load() && rt.bridge_on_host() && !warned_unbridged_udp_) {
      warned_unbridged_udp_ = true;
      spdlog::warn("lcmx: topic '{}' is large: sending it as UDP fragments to {} subscriber(s) on hosts "
                   "where no Message Bridge republishes it (none runs there, or it is no peer of this "
                   "host's; start `lcmx bridge` on every host)",
                   channel_, unbridged_udp_subscribers_.load());
    }
    if (vehicle_marker_due_.exchange(false)) rt.markers.baseline(*rt.vehicle_group, true, channel_);
    sent.vehicle = send(*rt.vehicle_group, "vehicle");
  }
  // The mirror, and subscribers of neighbours (this network namespace, another /dev/shm).
  if (mirrors(encoded.size()) || local_udp_subscribers_.load() > 0) {
    if (local_udp_subscribers_.load() > 0 && local_marker_due_.exchange(false))
      rt.markers.baseline(*rt.local_group, false, channel_);
    sent.local = send(*rt.local_group, "host-local");
  }
  return sent;
}

// Encodes once: straight into a shm slot when shm readers exist or messages are kept (UDP is
// sent from the same bytes before the commit), else into a reused buffer for UDP. Returns a
// copy of the encoding when keep last N keeps it for UDP replays (keeps_encoding), else null,
// and what went out over UDP. publish_mu held.
PublisherImpl::Written PublisherImpl::write_encoded(const void* object, std::size_t size, bool shm, bool udp) {
  Written out;
  if (shm) {
    try {
      auto loan = writer_->loan(size);
      type.encode(object, loan.data(), size);
      if (udp) out.sent = send_udp({loan.data(), size});
      if (keeps_encoding()) out.kept = make_bytes({loan.data(), size});
      writer_->commit(std::move(loan), size, slot_flags());  // after note_size: this message's class
    } catch (const shm::Error& e) {
      throw Error(Errc::transport, "publish on '" + channel_ + "': " + e.what());
    }
    note_generation();
  } else if (udp) {
    udp_buf_.resize(size);
    type.encode(object, udp_buf_.data(), size);
    out.sent = send_udp(udp_buf_);
  }
  return out;
}

bool PublisherImpl::keeps_encoding() const {
  return options.history > 0 && !(large_.load() && node->runtime->bridge_on_host());
}

void PublisherImpl::keep(std::shared_ptr<const void> object, std::shared_ptr<const Bytes> encoded,
                         UdpSent sent) {
  kept_.push_back({std::move(object), std::move(encoded), sent.vehicle, sent.local});
  while (kept_.size() > options.history) kept_.pop_front();
}

std::vector<PublisherImpl::KeptUdp> PublisherImpl::kept_for_udp(bool vehicle) const {
  std::lock_guard lock(publish_mu);
  std::vector<KeptUdp> out;
  for (const auto& k : kept_)
    if (k.encoded) out.push_back({k.encoded, vehicle ? k.vehicle_sequence : k.local_sequence});
  return out;
}

// A larger message moved the writer to a new segment generation: announce its name at once
// so subscribers that join now open the right one.
void PublisherImpl::note_generation() {
  shm_dropped_.store(writer_->dropped(), std::memory_order_relaxed);
  if (writer_->segment_name() == announced_segment_) return;
  announced_segment_ = writer_->segment_name();
  node->runtime->changed();
}

void PublisherImpl::publish_ref(const void* object,
                                std::shared_ptr<const void> (*copy)(const void*)) {
  // Targets are read under publish_mu: a subscriber matched meanwhile (add_intra, which
  // hands over the kept messages under publish_mu) gets this message exactly once.
  auto lock = lock_no_loan("publish");
  auto t = targets();
  const bool history = options.history > 0;
  const bool shm = history || writer_->registered_readers() > 0 || in_startup();
  const std::size_t size = type.encoded_size(object);
  // Checked and classified first, even when it is not encoded (in-process subscribers only, or
  // none): a Message Bridge lists the large topics of its host for its peers' pattern
  // subscribers (docs/bridge.md "Pattern subscribers"), and the message that turns the topic
  // large goes where large ones go (not over UDP and through the bridges both).
  check_size(size);
  note_size(size);
  const bool udp = wants_udp(size);
  // In-process subscribers first: handing over a pointer is cheaper than encoding.
  std::shared_ptr<const void> shared;
  if (!t->empty() || history) shared = copy(object);
  if (!t->empty()) deliver_intra(*t, shared);
  Written w;
  if (shm || udp) w = write_encoded(object, size, shm, udp);
  if (history) keep(std::move(shared), std::move(w.kept), w.sent);
  published_.fetch_add(1);
}

void PublisherImpl::publish_shared(std::shared_ptr<const void> object) {
  if (!object) throw Error(Errc::invalid_argument, "publish on '" + channel_ + "': null message");
  auto lock = lock_no_loan("publish");  // then the targets: see publish_ref
  auto t = targets();
  const bool history = options.history > 0;
  const bool shm = history || writer_->registered_readers() > 0 || in_startup();
  const std::size_t size = type.encoded_size(object.get());
  check_size(size);  // as publish_ref
  note_size(size);
  const bool udp = wants_udp(size);
  if (!t->empty()) deliver_intra(*t, object);
  Written w;
  if (shm || udp) w = write_encoded(object.get(), size, shm, udp);
  if (history) keep(std::move(object), std::move(w.kept), w.sent);
  published_.fetch_add(1);
}

void PublisherImpl::publish_bytes(std::span<const std::byte> data) {
  check_size(data.size());
  auto lock = lock_no_loan("publish");  // then the targets: see publish_ref
  auto t = targets();
  note_size(data.size());
  const bool history = options.history > 0;
  if (history || writer_->registered_readers() > 0 || in_startup()) {
    try {
      writer_->write(data.data(), data.size(), slot_flags());
    } catch (const shm::Error& e) {
      throw Error(Errc::transport, "publish on '" + channel_ + "': " + e.what());
    }
    note_generation();
  }
  UdpSent sent;
  if (wants_udp(data.size())) sent = send_udp(data);
  std::shared_ptr<const Bytes> copy;
  if (!t->empty() || history) copy = make_bytes(data);
  if (!t->empty()) deliver_intra(*t, copy);
  if (history) keep(copy, keeps_encoding() ? copy : nullptr, sent);
  published_.fetch_add(1);
}

// publish_mu, once no Loan is out (see PublisherCore::loan). Throws Error(invalid_argument)
// if the calling thread holds the Loan.
std::unique_lock<std::mutex> PublisherImpl::lock_no_loan(const char* what) {
  std::unique_lock lock(publish_mu);
  if (loan_out_ && loan_thread_ == std::this_thread::get_id())
    throw Error(Errc::invalid_argument,
                std::string(what) + " on '" + channel_ +
                    "': this thread holds a Loan of the publisher; publish or drop it first");
  loan_cv_.wait(lock, [&] { return !loan_out_; });
  return lock;
}

shm::WriteLoan PublisherImpl::loan(std::size_t size) {
  check_size(size);
  auto lock = lock_no_loan("loan");
  try {
    auto loan = writer_->loan(size);
    note_generation();
    loan_out_ = true;
    loan_thread_ = std::this_thread::get_id();
    return loan;
  } catch (const shm::Error& e) {
    throw Error(Errc::transport, "loan on '" + channel_ + "': " + e.what());
  }
}

void PublisherImpl::publish_loan(shm::WriteLoan&& loan, std::size_t size) {
  if (size > loan.capacity())
    throw Error(Errc::invalid_argument, "publish on '" + channel_ + "': size " +
                                            std::to_string(size) + " exceeds the loan's capacity");
  std::lock_guard lock(publish_mu);
  auto t = targets();  // under publish_mu: see publish_ref
  note_size(size);
  // In-process subscribers get a copy taken before the slot is handed to other processes.
  // If this throws, the loan stays out: the Loan's destructor drops it.
  const bool history = options.history > 0;
  std::shared_ptr<const Bytes> copy;
  if (!t->empty() || history) copy = make_bytes({loan.data(), size});
  if (!t->empty()) deliver_intra(*t, copy);
  UdpSent sent;
  if (wants_udp(size)) sent = send_udp({loan.data(), size});
  if (history) keep(copy, keeps_encoding() ? copy : nullptr, sent);
  auto end = [&] {  // committed or refused: the loan is over, waiting publishers go on
    loan_out_ = false;
    loan_cv_.notify_all();
  };
  try {
    writer_->commit(std::move(loan), size, slot_flags());
    shm_dropped_.store(writer_->dropped(), std::memory_order_relaxed);
  } catch (const shm::Error& e) {
    end();
    throw Error(Errc::transport, "publish on '" + channel_ + "': " + e.what());
  }
  end();
  published_.fetch_add(1);
}

void PublisherImpl::drop_loan(shm::WriteLoan&& loan) noexcept {
  std::lock_guard lock(publish_mu);
  { shm::WriteLoan gone = std::move(loan); }  // gives the slot back (Writer used under publish_mu)
  loan_out_ = false;
  loan_cv_.notify_all();
}

std::size_t PublisherImpl::subscriber_count() const {
  std::lock_guard lock(intra_mu);
  return intra_->size() + remote_subscribers_;
}

bool PublisherImpl::wait_for_subscribers(std::size_t n, std::chrono::milliseconds timeout) const {
  std::unique_lock lock(intra_mu);
  return subs_cv.wait_for(lock, timeout,
                          [&] { return intra_->size() + remote_subscribers_ >= n; });
}

// Keep last N: the kept messages are handed over under publish_mu, so each message published
// around the match reaches the new subscriber once, either kept or live (publishers read
// their targets under publish_mu). A Loan out does not hold this up: its publish comes later.
void PublisherImpl::add_intra(std::shared_ptr<SubscriberCore> sub, std::shared_ptr<PairCounters> stats) {
  std::unique_lock<std::mutex> publishing;
  if (options.history > 0) publishing = std::unique_lock(publish_mu);
  {
    std::lock_guard lock(intra_mu);
    auto next = std::make_shared<Targets>(*intra_);
    next->push_back({sub, stats});
    if (interrupt_on_match.load()) node->interrupt();
    intra_ = std::move(next);
    subs_cv.notify_all();
  }
  for (const auto& k : kept_) {
    std::span<const std::byte> bytes;
    if (type.carries_bytes()) bytes = *std::static_pointer_cast<const Bytes>(k.object);
    push_intra(*sub, IntraItem{k.object, &type, stats, bytes});
  }
}

void PublisherImpl::remove_intra(const SubscriberCore* sub) {
  std::lock_guard lock(intra_mu);
  auto next = std::make_shared<Targets>(*intra_);
  std::erase_if(*next, [&](const IntraTarget& t) { return t.sub.get() == sub; });
  if (interrupt_on_match.load()) node->interrupt();
  intra_ = std::move(next);
  subs_cv.notify_all();
}

void PublisherImpl::set_remote_subscribers(std::size_t shm, std::size_t udp, std::size_t local_udp,
                                           std::size_t unbridged_udp, std::size_t unbridged_elsewhere) {
  std::lock_guard lock(intra_mu);
  if (remote_subscribers_ != shm + udp + local_udp && interrupt_on_match.load()) node->interrupt();
  remote_subscribers_ = shm + udp + local_udp;
  if (udp > udp_subscribers_.load()) vehicle_marker_due_.store(true);
  if (local_udp > local_udp_subscribers_.load()) local_marker_due_.store(true);
  udp_subscribers_.store(udp);
  unbridged_udp_subscribers_.store(unbridged_udp);
  unbridged_elsewhere_.store(unbridged_elsewhere);
  local_udp_subscribers_.store(local_udp);
  subs_cv.notify_all();
}

std::shared_ptr<const Bytes> make_bytes(std::span<const std::byte> data) {
  return std::make_shared<const Bytes>(data.begin(), data.end());
}

void push_intra(SubscriberCore& sub, IntraItem item) {
  auto& st = *sub.state;
  std::shared_ptr<NodeImpl> node;
  {
    std::lock_guard lock(st.mu);
    if (st.removed.load()) return;
    if (st.queue.size() >= std::max<std::size_t>(sub.options().queue_depth, 1)) {
      if (sub.options().policy == QueuePolicy::drop_newest) {
        item.pair->drops.fetch_add(1);
        return;
      }
      st.queue.front().pair->drops.fetch_add(1);
      st.queue.pop_front();
    }
    st.queue.push_back(std::move(item));
    st.queued.store(true, std::memory_order_release);
    node = st.node;
  }
  if (node) node->ring();
}

}  // namespace lcmx::detail
