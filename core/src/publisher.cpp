#include <spdlog/spdlog.h>

#include <cstring>

#include "internal.hpp"

namespace lcmx::detail {

PublisherImpl::PublisherImpl(std::shared_ptr<NodeImpl> n, std::string channel,
                             const TypeInfo& t, PublisherOptions o)
    : node(std::move(n)), id(node->runtime->new_endpoint_id()), type(t), options(o),
      channel_(std::move(channel)) {
  if (options.max_message_size == 0)
    throw Error(Errc::invalid_argument, "publisher '" + channel_ + "': max_message_size is 0");
  shm::WriterOptions w;
  w.slot_count = options.shm_slots;
  w.initial_slot_size = std::min(options.shm_initial_slot_size, options.max_message_size);
  w.max_message_size = options.max_message_size;
  try {
    writer_.emplace(shm::Writer::create(node->runtime->shm_base_prefix + std::to_string(id), w));
    announced_segment_ = writer_->segment_name();
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
  for (const auto& target : t) push_intra(*target.sub, IntraItem{object, &type, target.stats});
}

// Encodes straight into a shm slot (no staging copy). publish_mu held.
void PublisherImpl::write_encoded(const void* object) {
  const std::size_t size = type.encoded_size(object);
  check_size(size);
  try {
    auto loan = writer_->loan(size);
    type.encode(object, loan.data(), size);
    writer_->commit(std::move(loan), size);
  } catch (const shm::Error& e) {
    throw Error(Errc::transport, "publish on '" + channel_ + "': " + e.what());
  }
  note_generation();
}

// A larger message moved the writer to a new segment generation: announce its name at once
// so subscribers that join now open the right one.
void PublisherImpl::note_generation() {
  if (writer_->segment_name() == announced_segment_) return;
  announced_segment_ = writer_->segment_name();
  node->runtime->changed();
}

void PublisherImpl::publish_ref(const void* object,
                                std::shared_ptr<const void> (*copy)(const void*)) {
  auto t = targets();
  std::lock_guard lock(publish_mu);
  const bool shm = writer_->registered_readers() > 0;
  if (!shm) check_size(type.encoded_size(object));  // also when only in-process subscribers
  // In-process subscribers first: handing over a pointer is cheaper than encoding.
  if (!t->empty()) deliver_intra(*t, copy(object));
  if (shm) write_encoded(object);
  published_.fetch_add(1);
}

void PublisherImpl::publish_shared(std::shared_ptr<const void> object) {
  if (!object) throw Error(Errc::invalid_argument, "publish on '" + channel_ + "': null message");
  auto t = targets();
  std::lock_guard lock(publish_mu);
  const bool shm = writer_->registered_readers() > 0;
  if (!shm) check_size(type.encoded_size(object.get()));
  if (!t->empty()) deliver_intra(*t, object);
  if (shm) write_encoded(object.get());
  published_.fetch_add(1);
}

void PublisherImpl::publish_bytes(std::span<const std::byte> data) {
  check_size(data.size());
  auto t = targets();
  std::lock_guard lock(publish_mu);
  if (writer_->registered_readers() > 0) {
    try {
      writer_->write(data.data(), data.size());
    } catch (const shm::Error& e) {
      throw Error(Errc::transport, "publish on '" + channel_ + "': " + e.what());
    }
    note_generation();
  }
  if (!t->empty()) deliver_intra(*t, make_bytes(data));
  published_.fetch_add(1);
}

shm::WriteLoan PublisherImpl::loan(std::size_t size) {
  check_size(size);
  std::lock_guard lock(publish_mu);
  try {
    auto loan = writer_->loan(size);
    note_generation();
    return loan;
  } catch (const shm::Error& e) {
    throw Error(Errc::transport, "loan on '" + channel_ + "': " + e.what());
  }
}

void PublisherImpl::publish_loan(shm::WriteLoan&& loan, std::size_t size) {
  if (size > loan.capacity())
    throw Error(Errc::invalid_argument, "publish on '" + channel_ + "': size " +
                                            std::to_string(size) + " exceeds the loan's capacity");
  auto t = targets();
  std::lock_guard lock(publish_mu);
  // In-process subscribers get a copy taken before the slot is handed to other processes.
  if (!t->empty()) deliver_intra(*t, make_bytes({loan.data(), size}));
  writer_->commit(std::move(loan), size);
  published_.fetch_add(1);
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

void PublisherImpl::add_intra(std::shared_ptr<SubscriberCore> sub, std::shared_ptr<PairCounters> stats) {
  std::lock_guard lock(intra_mu);
  auto next = std::make_shared<Targets>(*intra_);
  next->push_back({std::move(sub), std::move(stats)});
  intra_ = std::move(next);
  subs_cv.notify_all();
}

void PublisherImpl::remove_intra(const SubscriberCore* sub) {
  std::lock_guard lock(intra_mu);
  auto next = std::make_shared<Targets>(*intra_);
  std::erase_if(*next, [&](const IntraTarget& t) { return t.sub.get() == sub; });
  intra_ = std::move(next);
  subs_cv.notify_all();
}

void PublisherImpl::set_remote_subscribers(std::size_t n) {
  std::lock_guard lock(intra_mu);
  remote_subscribers_ = n;
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
      st.queue.front().pair->drops.fetch_add(1);
      st.queue.pop_front();
    }
    st.queue.push_back(std::move(item));
    node = st.node;
  }
  if (node) node->ring();
}

}  // namespace lcmx::detail
