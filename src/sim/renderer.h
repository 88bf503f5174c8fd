// Headless rendering of a World's cameras with OSMesa (software OpenGL).
//
// Thread-safety: an OSMesa context is current on one thread at a time. Use one Renderer per
// thread (it is cheap to keep one per worker); a Renderer may move between threads only if the
// caller guarantees no concurrent use. render() makes its context current on the calling thread
// each time, so several Renderers may be used alternately on one thread.
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

namespace dojo::sim {

class World;

class Renderer {
 public:
  Renderer();
  ~Renderer();
  Renderer(const Renderer&) = delete;
  Renderer& operator=(const Renderer&) = delete;

  // RGB image of a camera of the scene ("ego", or "side": sim/scene_mjcf.cpp) at the scene's
  // width x height: [H, W, 3] uint8, row-major, top row first. Throws dojo::Error if OSMesa or
  // the MuJoCo GL context cannot be created, or the camera does not exist.
  std::vector<uint8_t> render(const World& world, const char* camera = "ego");
  // Same, into a caller-owned buffer of width * height * 3 bytes.
  void render_into(const World& world, uint8_t* rgb, const char* camera = "ego");

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace dojo::sim
