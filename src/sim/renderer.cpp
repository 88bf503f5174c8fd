#include "sim/renderer.h"

#include <GL/osmesa.h>
#include <mujoco/mujoco.h>

#include <cstring>

#include "core/error.h"
#include "sim/world.h"

namespace dojo::sim {

struct Renderer::Impl {
  OSMesaContext context = nullptr;
  std::vector<uint8_t> window;  // OSMesa's own colour buffer (MuJoCo draws into an offscreen FBO)
  int window_w = 0, window_h = 0;
  uint64_t world_id = 0;  // the world whose model is uploaded into `gl`
  bool has_gl = false;
  mjvScene scene;
  mjvCamera camera;
  int ego_camera = -1;
  mjvOption option;
  mjrContext gl;
  std::vector<uint8_t> flipped;

  Impl() {
    mjv_defaultScene(&scene);
    mjv_defaultCamera(&camera);
    mjv_defaultOption(&option);
    mjr_defaultContext(&gl);
  }

  void free_model_state() {
    if (has_gl) {
      make_current(window_w, window_h);
      mjr_freeContext(&gl);
      mjv_freeScene(&scene);
      has_gl = false;
      world_id = 0;
    }
  }

  ~Impl() {
    free_model_state();
    if (context) OSMesaDestroyContext(context);
  }

  void make_current(int w, int h) {
    if (!context) {
      context = OSMesaCreateContextExt(OSMESA_RGBA, 24, 8, 0, nullptr);
      if (!context) throw Error("renderer: OSMesaCreateContextExt failed");
    }
    if (w != window_w || h != window_h) {
      window.assign(static_cast<size_t>(w) * h * 4, 0);
      window_w = w;
      window_h = h;
    }
    if (!OSMesaMakeCurrent(context, window.data(), GL_UNSIGNED_BYTE, w, h)) {
      throw Error("renderer: OSMesaMakeCurrent failed");
    }
  }

  void prepare(const World& world) {
    const int w = world.spec().width, h = world.spec().height;
    if (has_gl && world.id() == world_id && w == window_w && h == window_h) {
      if (OSMesaGetCurrentContext() != context) make_current(w, h);
      return;
    }
    free_model_state();
    make_current(w, h);
    const mjModel* m = world.model();
    mjv_makeScene(m, &scene, 2000);
    mjr_makeContext(m, &gl, mjFONTSCALE_50);
    has_gl = true;
    world_id = world.id();
    mjr_setBuffer(mjFB_OFFSCREEN, &gl);
    if (gl.currentBuffer != mjFB_OFFSCREEN)
      throw Error("renderer: offscreen framebuffer not supported by OSMesa");
    if (gl.offWidth < w || gl.offHeight < h) {
      throw Error("renderer: offscreen buffer " + std::to_string(gl.offWidth) + "x" +
                  std::to_string(gl.offHeight) + " smaller than the requested image");
    }
    // Shadows and reflections cost most of the software-rendering time and add little here.
    scene.flags[mjRND_SHADOW] = 0;
    scene.flags[mjRND_REFLECTION] = 0;
    scene.flags[mjRND_SKYBOX] = 1;
    camera.type = mjCAMERA_FIXED;
    camera.fixedcamid = ego_camera = mj_name2id(m, mjOBJ_CAMERA, "ego");
    if (camera.fixedcamid < 0) throw Error("renderer: model has no camera named 'ego'");
    // Only geom groups 0-2 are shown; sites (the grasp marker) stay hidden.
    for (int i = 0; i < mjNGROUP; ++i) option.sitegroup[i] = 0;
  }
};

Renderer::Renderer() : impl_(std::make_unique<Impl>()) {}
Renderer::~Renderer() = default;

std::vector<uint8_t> Renderer::render(const World& world, const char* camera) {
  std::vector<uint8_t> rgb(static_cast<size_t>(world.spec().width) * world.spec().height * 3);
  render_into(world, rgb.data(), camera);
  return rgb;
}

void Renderer::render_into(const World& world, uint8_t* rgb, const char* camera) {
  Impl& s = *impl_;
  s.prepare(world);
  if (std::strcmp(camera, "ego") != 0) {
    s.camera.fixedcamid = mj_name2id(world.model(), mjOBJ_CAMERA, camera);
    if (s.camera.fixedcamid < 0)
      throw Error(std::string("renderer: the scene has no camera named '") + camera + "'");
  } else {
    s.camera.fixedcamid = s.ego_camera;
  }
  const int w = world.spec().width, h = world.spec().height;
  mjrRect viewport = {0, 0, w, h};
  // mjv_updateScene only reads the data (it takes a non-const pointer for historical reasons).
  mjv_updateScene(world.model(), const_cast<mjData*>(world.data()), &s.option, nullptr, &s.camera, mjCAT_ALL,
                  &s.scene);
  mjr_render(viewport, &s.scene, &s.gl);
  s.flipped.resize(static_cast<size_t>(w) * h * 3);
  mjr_readPixels(s.flipped.data(), nullptr, viewport, &s.gl);
  // OpenGL rows start at the bottom.
  const size_t row = static_cast<size_t>(w) * 3;
  for (int y = 0; y < h; ++y) std::memcpy(rgb + y * row, s.flipped.data() + (h - 1 - y) * row, row);
}

}  // namespace dojo::sim
