// The LCM drop-in's C++ half (lcmx.LCM in python/lcmx/__init__.py): one node whose channel
// subscriptions (a regex) copy each message into a queue with an eventfd (fileno(), readable
// while the queue is not empty); handle() pops one and calls its handler on the caller's thread.
#include <sys/eventfd.h>
#include <unistd.h>

#include <condition_variable>
#include <deque>
#include <map>
#include <mutex>
#include <regex>

#include "binding.hpp"

namespace lcmxpy {
namespace {

struct PyLcm final : Closable {
  struct Sub {
    std::uint64_t id = 0;
    lcmx::ChannelSubscription subscription;
    py::object handler;  // GIL
    std::size_t capacity = 30;
    std::atomic<std::size_t> queued{0};
    std::atomic<std::uint64_t> dropped{0};
  };
  struct Item {
    std::shared_ptr<Sub> sub;
    std::string channel;
    std::vector<std::byte> data;
  };

  std::shared_ptr<PyRuntime> runtime;
  std::optional<lcmx::Node> node;
  std::map<std::string, lcmx::RawPublisher> pubs;  // GIL
  std::map<std::uint64_t, std::shared_ptr<Sub>> subs;  // GIL
  std::uint64_t next_id = 1;
  int efd = -1;  // readable while the queue is not empty
  std::mutex mu;
  std::condition_variable cv;
  std::deque<Item> queue;

  PyLcm() {
    efd = ::eventfd(0, EFD_CLOEXEC | EFD_NONBLOCK);
    if (efd < 0) throw lcmx::Error(lcmx::Errc::transport, "lcmx.LCM: eventfd failed");
  }
  ~PyLcm() override {
    if (!g_exiting.load()) {
      for (auto& [id, s] : subs) s->handler = py::object();
      py::gil_scoped_release nogil;
      drop_cpp();
    } else {
      for (auto& [id, s] : subs) s->handler.release();
    }
    if (efd >= 0) ::close(efd);
  }
  void drop_cpp() {
    for (auto& [id, s] : subs) s->subscription.reset();
    pubs.clear();
    node.reset();
  }
  void close() override {
    std::map<std::uint64_t, std::shared_ptr<Sub>> old;
    old.swap(subs);
    for (auto& [id, s] : old) s->handler = py::object();
    py::gil_scoped_release nogil;
    for (auto& [id, s] : old) s->subscription.reset();
    pubs.clear();
    node.reset();
  }
  bool closed() const override { return !node; }
  lcmx::Node& get() {
    if (!node) throw lcmx::Error(lcmx::Errc::invalid_argument, "the lcmx.LCM is closed");
    return *node;
  }

  void publish(const std::string& channel, const py::buffer& data) {
    auto& n = get();
    auto it = pubs.find(channel);
    if (it == pubs.end()) it = pubs.emplace(channel, n.advertise_raw(channel)).first;
    py::buffer_info info = data.request();
    std::span<const std::byte> bytes(static_cast<const std::byte*>(info.ptr),
                                     static_cast<std::size_t>(info.size * info.itemsize));
    lcmx::RawPublisher pub = it->second;  // our own handle: close() may clear pubs meanwhile
    py::gil_scoped_release nogil;
    pub.publish(bytes);
  }

  std::shared_ptr<Sub> subscribe(const std::string& pattern, py::object handler) {
    auto& n = get();
    auto re = std::make_shared<std::regex>(pattern, std::regex::ECMAScript);  // throws on a bad regex
    auto s = std::make_shared<Sub>();
    s->id = next_id++;
    s->handler = std::move(handler);
    std::weak_ptr<Sub> weak = s;
    s->subscription = n.subscribe_channels(
        [re](const std::string& channel) { return std::regex_match(channel, *re); },
        [this, weak](const lcmx::RawMessage& m) {  // executor thread, no GIL
          auto sub = weak.lock();
          if (!sub) return;
          if (sub->queued.load() >= sub->capacity && sub->capacity > 0) {
            sub->dropped.fetch_add(1);
            return;
          }
          Item item{sub, std::string(m.channel), std::vector<std::byte>(m.data.begin(), m.data.end())};
          std::lock_guard lock(mu);
          sub->queued.fetch_add(1);
          if (queue.empty()) {
            const std::uint64_t one = 1;
            [[maybe_unused]] auto w = ::write(efd, &one, sizeof one);
          }
          queue.push_back(std::move(item));
          cv.notify_one();
        });
    subs.emplace(s->id, s);
    return s;
  }

  void unsubscribe(const std::shared_ptr<Sub>& s) {
    if (!s || subs.erase(s->id) == 0)
      throw lcmx::Error(lcmx::Errc::invalid_argument, "unsubscribe: not a subscription of this LCM");
    s->handler = py::object();
    py::gil_scoped_release nogil;
    s->subscription.reset();
  }

  // Pops one message (waiting up to `timeout`); GIL not held.
  std::optional<Item> pop(std::chrono::nanoseconds timeout) {
    std::unique_lock lock(mu);
    if (!cv.wait_for(lock, timeout, [&] { return !queue.empty(); })) return std::nullopt;
    Item item = std::move(queue.front());
    queue.pop_front();
    item.sub->queued.fetch_sub(1);
    if (queue.empty()) {
      std::uint64_t v;
      [[maybe_unused]] auto r = ::read(efd, &v, sizeof v);
    }
    return item;
  }

  // Handles one message; returns false if none came within `timeout` (None: forever).
  bool handle(std::optional<double> timeout_s) {
    get();
    std::optional<Item> item;
    const bool got = wait_interruptible(timeout_s, [&](std::chrono::nanoseconds slice) {
      item = pop(slice);
      return item.has_value();
    });
    if (!got) return false;
    if (!item->sub->handler) return true;  // unsubscribed since: consumed, like LCM
    py::bytes data(reinterpret_cast<const char*>(item->data.data()), item->data.size());
    item->sub->handler(item->channel, data);  // exceptions propagate, as in LCM's handle()
    return true;
  }
};

}  // namespace

void bind_lcm(py::module_& m) {
  py::class_<PyLcm::Sub, std::shared_ptr<PyLcm::Sub>>(m, "LCMSubscription")
      .def("set_queue_capacity", [](PyLcm::Sub& s, std::size_t n) { s.capacity = n; })
      .def_property_readonly("dropped", [](PyLcm::Sub& s) { return s.dropped.load(); });

  py::class_<PyLcm, std::shared_ptr<PyLcm>>(m, "_LCM")
      .def(py::init([](std::shared_ptr<PyRuntime> runtime) {
        auto l = std::make_shared<PyLcm>();
        l->runtime = std::move(runtime);
        l->node.emplace(l->runtime->get().create_node("lcm"));
        l->runtime->adopt(l);
        return l;
      }))
      .def("close", &PyLcm::close)
      .def("publish", &PyLcm::publish, py::arg("channel"), py::arg("data"))
      .def("subscribe", &PyLcm::subscribe, py::arg("channel"), py::arg("handler"))
      .def("unsubscribe", &PyLcm::unsubscribe, py::arg("subscription"))
      .def("handle", [](PyLcm& l, std::optional<double> timeout) { return l.handle(timeout); },
           py::arg("timeout") = py::none())
      .def("fileno", [](PyLcm& l) { return l.efd; });
}

}  // namespace lcmxpy
