// The serve tests' one wait for a server to free its sessions.
#pragma once

#include <chrono>
#include <thread>

#include "serve/server.h"

namespace dojo::test {

// A server frees a session just after its client has gone; a test that then needs the slot (a
// session cap) waits for that, up to 5 s. Returns whether every session is gone.
inline bool sessions_drained(serve::Server& server) {
  for (int i = 0; i < 500 && server.metrics().sessions_active() > 0; ++i)
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  return server.metrics().sessions_active() == 0;
}

}  // namespace dojo::test
