// Services over raw bytes (typed in python/lcmx/__init__.py): _Service, _Client, and
// Node.create_service_raw / Node.create_client_raw. A typed service announces its lcm-gen types
// (service_types), so matching and type_mismatch are core's.
#include <cstring>
#include <future>

#include "binding.hpp"

namespace lcmxpy {
namespace {

struct PyService final : Closable {
  std::shared_ptr<lcmx::Service> svc;
  std::shared_ptr<CallbackBox> box;
  bool closed() const override { return !svc; }
  void close() override {
    if (box) box->clear();
    auto old = std::move(svc);
    drop(old);
  }
  ~PyService() override {
    if (svc && !g_exiting.load()) {
      if (box) box->clear();
      drop(svc);
    }
  }
};

struct PyClient final : Closable {
  std::shared_ptr<lcmx::RawClient> cli;
  bool closed() const override { return !cli; }
  std::shared_ptr<lcmx::RawClient> get() {
    if (!cli) throw lcmx::Error(lcmx::Errc::invalid_argument, "the lcmx client is closed");
    return cli;
  }
  void close() override {
    auto old = std::move(cli);
    drop(old);
  }
  ~PyClient() override {
    if (cli && !g_exiting.load()) drop(cli);
  }
};

// None: raw bytes; else (request_name, response_name, request_fingerprint, response_fingerprint).
lcmx::detail::ServiceTypes service_types(const py::object& t) {
  if (t.is_none()) return {};
  auto v = t.cast<std::tuple<std::string, std::string, std::int64_t, std::int64_t>>();
  return {std::get<0>(v), std::get<1>(v), std::get<2>(v), std::get<3>(v)};
}

}  // namespace

void bind_services(py::module_& m, NodeClass& node) {
  py::class_<PyService, std::shared_ptr<PyService>>(m, "_Service")
      .def("close", &PyService::close)
      .def_property_readonly("handler_errors", [](PyService& s) { return s.box->errors.load(); });

  py::class_<PyClient, std::shared_ptr<PyClient>>(m, "_Client")
      .def("close", &PyClient::close)
      .def("wait_for_service",
           [](PyClient& c, double timeout) {
             return wait_on(c.get(), timeout, [](lcmx::RawClient& cli, std::chrono::nanoseconds slice) {
               return cli.wait_for_service(slice_ms(slice));
             });
           },
           py::arg("timeout") = 10.0)
      // Returns (True, response bytes, "", "", path) or (False, None, error code, message, path).
      .def("call",
           [](PyClient& c, const py::buffer& request, double timeout) {
             auto cli = c.get();
             py::buffer_info info = request.request();
             std::span<const std::byte> bytes(static_cast<const std::byte*>(info.ptr),
                                              static_cast<std::size_t>(info.size * info.itemsize));
             std::future<lcmx::RawClient::Result> fut;
             {
               py::gil_scoped_release nogil;
               fut = cli->call_async(bytes, std::chrono::duration_cast<std::chrono::milliseconds>(
                                                std::chrono::duration<double>(std::max(0.0, timeout))));
             }
             try {
               // The call ends by itself at its timeout; slices let Ctrl-C through meanwhile.
               wait_interruptible(std::nullopt, [&](std::chrono::nanoseconds slice) {
                 return fut.wait_for(slice) == std::future_status::ready;
               });
             } catch (...) {
               drop(cli);
               throw;
             }
             drop(cli);
             auto r = fut.get();
             const char* path = lcmx::to_string(r.server().path);
             if (!r.ok()) return py::make_tuple(false, py::none(), lcmx::to_string(r.error()), r.message(), path);
             const auto& v = r.value();
             return py::make_tuple(true, py::bytes(reinterpret_cast<const char*>(v.data()), v.size()), "", "", path);
           },
           py::arg("request"), py::arg("timeout") = 1.0);

  node.def("create_service_raw",
           [](const std::shared_ptr<PyNode>& n, std::string name, py::object handler, py::object types,
              py::object decode) {
             if (!PyCallable_Check(handler.ptr()))
               throw lcmx::Error(lcmx::Errc::invalid_argument, "create_service: the handler is not callable");
             auto t = service_types(types);
             auto box = std::make_shared<CallbackBox>();
             box->fn = std::move(handler);
             box->decode = std::move(decode);
             std::string where = name;
             std::string request_name = t.request_name;
             // On the node's executor. A request that `decode` refuses is bad_request; what
             // the handler raises reaches the client as handler_failed with its text.
             auto h = [box, where, request_name](std::span<const std::byte> in, lcmx::ResponseWriter& out) {
               if (g_exiting.load()) throw std::runtime_error("the Python interpreter is exiting");
               ExecutorGil gil;
               if (!box->fn) throw std::runtime_error("the service is closed");
               try {
                 py::object r;
                 with_view(in, [&](py::object& view) {
                   py::object arg = view;
                   if (box->decode && !box->decode.is_none()) arg = decode_or_bad_request(box->decode, view, request_name);
                   r = box->fn(arg);
                 });
                 if (!PyObject_CheckBuffer(r.ptr()))
                   throw std::runtime_error("the handler did not return a bytes-like object");
                 py::buffer_info info = py::reinterpret_borrow<py::buffer>(r).request();
                 const auto size = static_cast<std::size_t>(info.size * info.itemsize);
                 auto dst = out.allocate(size);
                 std::memcpy(dst.data(), info.ptr, size);
               } catch (py::error_already_set& e) {
                 report_callback_error(*box, where, e);
                 throw std::runtime_error(e.what());
               }
             };
             auto s = std::make_shared<PyService>();
             s->box = box;
             s->svc = std::make_shared<lcmx::Service>(
                 n->get()->create_service_raw(std::move(name), std::move(t), std::move(h)));
             n->runtime->adopt(s);
             return s;
           },
           py::arg("name"), py::arg("handler"), py::arg("types") = py::none(), py::arg("decode") = py::none())
      .def("create_client_raw",
           [](const std::shared_ptr<PyNode>& n, std::string name, py::object types) {
             auto c = std::make_shared<PyClient>();
             c->cli = std::make_shared<lcmx::RawClient>(n->get()->create_client_raw(std::move(name), service_types(types)));
             n->runtime->adopt(c);
             return c;
           },
           py::arg("name"), py::arg("types") = py::none());
}

}  // namespace lcmxpy
