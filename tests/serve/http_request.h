// The serve tests' one plain-HTTP client: a request to a server on 127.0.0.1.
#pragma once

#include <boost/asio/connect.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/beast/core.hpp>
#include <boost/beast/http.hpp>

#include <cstdint>
#include <string>

namespace dojo::test {

struct HttpResult {
  int status = 0;
  std::string body, content_type;
};

// One request to 127.0.0.1:port; a non-empty body goes as JSON, a non-empty bearer as the
// Authorization header, a non-empty cookie as the Cookie header.
inline HttpResult http_request(uint16_t port, boost::beast::http::verb verb, const std::string& target,
                               const std::string& body = "", const std::string& bearer = "",
                               const std::string& cookie = "") {
  namespace beast = boost::beast;
  namespace http = beast::http;
  namespace net = boost::asio;
  net::io_context ioc;
  beast::tcp_stream stream(ioc);
  stream.connect(net::ip::tcp::endpoint(net::ip::make_address("127.0.0.1"), port));
  http::request<http::string_body> req{verb, target, 11};
  req.set(http::field::host, "127.0.0.1");
  if (!bearer.empty()) req.set(http::field::authorization, "Bearer " + bearer);
  if (!cookie.empty()) req.set(http::field::cookie, cookie);
  if (!body.empty()) {
    req.set(http::field::content_type, "application/json");
    req.body() = body;
    req.prepare_payload();
  }
  http::write(stream, req);
  beast::flat_buffer buffer;
  http::response<http::string_body> res;
  http::read(stream, buffer, res);
  return {static_cast<int>(res.result_int()), res.body(), std::string(res[http::field::content_type])};
}

}  // namespace dojo::test
