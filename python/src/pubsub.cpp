// Publish/subscribe over raw bytes (typed in python/lcmx/__init__.py: lcm-gen classes' encode
// and decode): _Publisher, Loan (zero-copy publish), _Subscriber (a memoryview of the message,
// zero-copy on the shared-memory path), and Node.advertise_raw / Node.subscribe_raw.
#include <cstring>

#include "binding.hpp"

namespace lcmxpy {
namespace {

py::dict to_dict(const lcmx::SubscriberStats& s, std::uint64_t callback_errors) {
  py::dict d;
  d["delivered"] = s.delivered;
  d["drops"] = s.drops;
  d["decode_errors"] = s.decode_errors;
  d["callback_errors"] = callback_errors;
  d["errors"] = s.errors;
  py::list pubs;
  for (const auto& p : s.publishers) {
    py::dict e;
    e["participant"] = p.publisher_participant;
    e["endpoint"] = p.publisher_endpoint;
    e["path"] = lcmx::to_string(p.path);
    e["received"] = p.received;
    e["drops"] = p.drops;
    pubs.append(e);
  }
  d["publishers"] = pubs;
  return d;
}

struct PyPublisher final : Closable {
  std::shared_ptr<PyNode> node;
  std::shared_ptr<lcmx::RawPublisher> pub;
  bool closed() const override { return !pub; }
  std::shared_ptr<lcmx::RawPublisher> get() {
    if (!pub) throw lcmx::Error(lcmx::Errc::invalid_argument, "the lcmx publisher is closed");
    return pub;
  }
  void publish(const py::buffer& data) {
    lcmx::RawPublisher p = *get();  // a handle of our own (shares the publisher)
    py::buffer_info info = data.request();  // holds the buffer while the GIL is released
    if (!PyBuffer_IsContiguous(info.view(), 'C'))
      throw lcmx::Error(lcmx::Errc::invalid_argument, "publish: the buffer is not contiguous");
    std::span<const std::byte> bytes(static_cast<const std::byte*>(info.ptr),
                                     static_cast<std::size_t>(info.size * info.itemsize));
    py::gil_scoped_release nogil;
    p.publish(bytes);
  }
  void close() override {
    auto old = std::move(pub);
    drop(old);
  }
  ~PyPublisher() override {
    if (pub && !g_exiting.load()) {
      py::gil_scoped_release nogil;
      pub.reset();
    }
  }
};

// A slot loaned from a raw publisher (zero-copy publish): `view` is a writable memoryview of
// it until publish() or drop(), which release the view first and refuse (lcmx.Error) while
// something still exports it (e.g. a numpy array over it), since the slot is then reused.
struct PyLoan {
  lcmx::RawPublisher pub;  // a handle of our own (shares the publisher)
  lcmx::Loan loan;
  std::size_t size = 0;
  std::optional<SlotView> slot;  // GIL

  void release_view() {
    if (slot && !slot->try_release())
      throw lcmx::Error(lcmx::Errc::invalid_argument,
                        "the loan's memory is still referred to (a slice, cast or array of its view): "
                        "delete those first");
    if (slot) slot->revoke();
    slot.reset();
  }
  bool open() const { return loan.data() != nullptr; }
  void publish(std::optional<std::size_t> n) {
    if (!open()) throw lcmx::Error(lcmx::Errc::invalid_argument, "the loan was already published or dropped");
    const std::size_t bytes = n.value_or(size);
    if (bytes > size)
      throw lcmx::Error(lcmx::Errc::invalid_argument,
                        "publish: " + std::to_string(bytes) + " bytes from a loan of " + std::to_string(size));
    release_view();
    py::gil_scoped_release nogil;
    pub.publish(std::move(loan), bytes);
  }
  void drop() {
    if (!open()) return;
    release_view();
    py::gil_scoped_release nogil;
    loan = lcmx::Loan();
  }
  ~PyLoan() {
    // The loan's last Python reference is going (GIL held): revoke the memory, drop the slot.
    if (slot) slot->revoke();
    slot.reset();
    if (open() && !g_exiting.load()) {
      py::gil_scoped_release nogil;
      loan = lcmx::Loan();
    }
  }
};

struct PySubscriber final : Closable {
  std::shared_ptr<PyNode> node;
  std::shared_ptr<lcmx::RawSubscriber> sub;
  std::shared_ptr<CallbackBox> box;
  bool closed() const override { return !sub; }
  std::shared_ptr<lcmx::RawSubscriber> get() {
    if (!sub) throw lcmx::Error(lcmx::Errc::invalid_argument, "the lcmx subscriber is closed");
    return sub;
  }
  void close() override {
    if (box) box->clear();  // a callback waiting for the GIL then returns at once
    auto old = std::move(sub);
    drop(old);  // waits for a running callback (unless called from inside it)
  }
  ~PySubscriber() override {
    if (sub && !g_exiting.load()) {
      if (box) box->clear();
      py::gil_scoped_release nogil;
      sub.reset();
    }
  }
};

}  // namespace

void bind_pubsub(py::module_& m, NodeClass& node) {
  py::class_<PyPublisher, std::shared_ptr<PyPublisher>>(m, "_Publisher")
      .def("close", &PyPublisher::close)
      .def("publish", &PyPublisher::publish, py::arg("data"))
      .def("loan",
           [](PyPublisher& p, std::size_t size) {
             auto l = std::make_shared<PyLoan>();
             l->pub = *p.get();
             l->size = size;
             {
               py::gil_scoped_release nogil;
               l->loan = l->pub.loan(size);
             }
             l->slot.emplace(l->loan.data(), size, false);
             return l;
           },
           py::arg("size"))
      .def_property_readonly("channel", [](PyPublisher& p) { return p.get()->channel(); })
      .def("subscriber_count", [](PyPublisher& p) { return p.get()->subscriber_count(); })
      .def("wait_for_subscribers",
           [](PyPublisher& p, std::size_t n, double timeout) {
             lcmx::RawPublisher pub = *p.get();  // publisher handles copy (shared)
             return wait_interruptible(timeout, [&](std::chrono::nanoseconds slice) {
               return pub.wait_for_subscribers(n, std::chrono::duration_cast<std::chrono::milliseconds>(slice));
             });
           },
           py::arg("n") = 1, py::arg("timeout") = 10.0)
      .def("stats", [](PyPublisher& p) {
        const auto s = p.get()->stats();
        py::dict d;
        d["published"] = s.published;
        d["shm_dropped"] = s.shm_dropped;
        return d;
      });

  py::class_<PyLoan, std::shared_ptr<PyLoan>>(m, "Loan")
      .def_property_readonly("view", [](PyLoan& l) -> py::object {
        if (!l.open() || !l.slot) throw lcmx::Error(lcmx::Errc::invalid_argument, "the loan was already published or dropped");
        return l.slot->view;
      })
      .def_property_readonly("size", [](PyLoan& l) { return l.size; })
      .def("publish", &PyLoan::publish, py::arg("size") = py::none())
      .def("drop", &PyLoan::drop)
      // The context manager (lcmx.Loan): yields the view, publishes on a normal exit, drops on
      // an exception. In C++: it is on the path of every loaned message.
      .def("__enter__", [](PyLoan& l) -> py::object {
        if (!l.open() || !l.slot) throw lcmx::Error(lcmx::Errc::invalid_argument, "the loan was already published or dropped");
        return l.slot->view;
      })
      .def("__exit__", [](PyLoan& l, py::handle type, py::handle, py::handle) {
        if (type.is_none()) l.publish(std::nullopt);
        else l.drop();
        return false;
      });

  py::class_<PySubscriber, std::shared_ptr<PySubscriber>>(m, "_Subscriber")
      .def("close", &PySubscriber::close)
      .def_property_readonly("channel", [](PySubscriber& s) { return s.get()->channel(); })
      .def("publisher_count", [](PySubscriber& s) { return s.get()->publisher_count(); })
      .def("wait_for_publishers",
           [](PySubscriber& s, std::size_t n, double timeout) {
             return wait_on(s.get(), timeout, [n](lcmx::RawSubscriber& sub, std::chrono::nanoseconds slice) {
               return sub.wait_for_publishers(n, slice_ms(slice));
             });
           },
           py::arg("n") = 1, py::arg("timeout") = 10.0)
      .def("stats", [](PySubscriber& s) {
        lcmx::SubscriberStats st;
        {
          auto sub = s.get();
          py::gil_scoped_release nogil;
          st = sub->stats();
          sub.reset();
        }
        return to_dict(st, s.box ? s.box->errors.load() : 0);
      });

  node.def("advertise_raw",
           [](const std::shared_ptr<PyNode>& n, std::string channel, std::optional<std::string> type_name,
              std::int64_t fingerprint, std::size_t max_message_size, std::uint32_t shm_slots,
              std::uint32_t history) {
             lcmx::PublisherOptions o;
             o.max_message_size = max_message_size;
             o.shm_slots = shm_slots;
             o.history = history;
             auto p = std::make_shared<PyPublisher>();
             p->node = n;
             auto node = n->get();
             p->pub = std::make_shared<lcmx::RawPublisher>(
                 type_name ? node->advertise_raw(std::move(channel), *type_name, fingerprint, o)
                           : node->advertise_raw(std::move(channel), o));
             n->runtime->adopt(p);
             return p;
           },
           py::arg("channel"), py::arg("type_name") = py::none(), py::arg("fingerprint") = 0,
           py::arg("max_message_size") = std::size_t{64} << 20, py::arg("shm_slots") = 8,
           py::arg("history") = 0)
      .def("subscribe_raw",
           [](const std::shared_ptr<PyNode>& n, std::string channel, py::object callback,
              std::optional<std::string> type_name, std::int64_t fingerprint, py::object decode,
              std::size_t queue_depth) {
             if (!PyCallable_Check(callback.ptr()))
               throw lcmx::Error(lcmx::Errc::invalid_argument, "subscribe: the callback is not callable");
             auto box = std::make_shared<CallbackBox>();
             box->fn = std::move(callback);
             box->decode = std::move(decode);
             std::string where = channel;
             auto cb = [box, where](const lcmx::RawMessage& msg) {  // executor thread
               if (g_exiting.load()) return;
               ExecutorGil gil;
               if (!box->fn) return;  // closed
               try {
                 with_view(msg.data, [&](py::object& view) {
                   if (box->decode && !box->decode.is_none()) {
                     py::object obj = box->decode(view);
                     box->fn(obj);
                   } else {
                     box->fn(view);
                   }
                 });
               } catch (py::error_already_set& e) {
                 report_callback_error(*box, where, e);
               }
             };
             lcmx::SubscriberOptions o;
             o.queue_depth = queue_depth;
             auto s = std::make_shared<PySubscriber>();
             s->node = n;
             s->box = box;
             auto node = n->get();
             s->sub = std::make_shared<lcmx::RawSubscriber>(
                 type_name ? node->subscribe_raw(std::move(channel), *type_name, fingerprint, cb, o)
                           : node->subscribe_raw(std::move(channel), cb, o));
             n->runtime->adopt(s);
             return s;
           },
           py::arg("channel"), py::arg("callback"), py::arg("type_name") = py::none(),
           py::arg("fingerprint") = 0, py::arg("decode") = py::none(), py::arg("queue_depth") = 16);
}

}  // namespace lcmxpy
