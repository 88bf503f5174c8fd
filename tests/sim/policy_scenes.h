// The evaluation's policy scenes as the sim tests use them: `count` scenes, scene i from seed + i.
#pragma once

#include <cstdint>
#include <vector>

#include "recipes/dojosim_policies.h"

namespace dojo::test {

inline std::vector<eval::EpisodeStart> policy_scenes(int64_t count, uint64_t seed = 7000) {
  recipes::PolicySceneOptions o;
  o.count = count;
  o.seed = seed;
  return recipes::make_policy_scenes(o);
}

}  // namespace dojo::test
