// The browser pages, compiled into the binary (generated from src/serve/pages/ by CMake), so a
// server needs no files beside it and the pages fetch nothing from the internet.
#pragma once

#include <string>
#include <vector>

namespace dojo::serve {

struct Page {
  const char* path;          // "/", "/teleop.js", ...
  const char* content_type;  // "text/html; charset=utf-8", ...
  std::string content;
};
const std::vector<Page>& embedded_pages();

}  // namespace dojo::serve
