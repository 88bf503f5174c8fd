// Task outcomes measured from simulator state: the robot's "put the objects in the bin" success
// and cheap per-object outcomes of human skills (displacement, toppled, lifted).
#pragma once

#include <array>
#include <vector>

#include <nlohmann/json_fwd.hpp>

#include "sim/world.h"

namespace dojo::sim {

// Speeds below which an object counts as resting.
constexpr double kRestLinearSpeed = 0.05;  // m/s
constexpr double kRestAngularSpeed = 0.8;  // rad/s

// How far above the rim an object's lowest point may be and still count as in the bin (an
// object resting on top of another one inside the bin).
constexpr double kBinStackAllowance = 0.04;

// The object's centre lies within the bin's inner walls and its lowest point is below the rim
// plus kBinStackAllowance. False when the scene has no bin.
bool object_in_bin(const World& world, int index);
bool object_resting(const World& world, int index);
// Fraction of objects that are in the bin, resting and not touched by the embodiment (so an
// object held still above the bin does not count), in [0, 1]; 0 for a scene without objects.
// Throws dojo::Error if the scene has no bin.
double bin_success(const World& world);

// The bin task's subtasks for object 0, in order: reach (the grasp point within 4 cm of the
// object's centre), lift (the object's lowest point 1.5 cm above the table, held), over the bin
// (lifted and its centre within the bin's walls), release (bin_success). The stage is how many of
// them the state shows, the last one reached counting: 0-4. The value model's subtask boundaries
// are the frames at which an episode first reaches a higher stage (policy planning,
// recipes/planning.h). Throws dojo::Error without a bin or an object.
constexpr int kBinTaskStages = 4;
int bin_task_stage(const World& world);

// Horizontal distance an object moved from `initial`.
double object_displacement(const ObjectPose& initial, const ObjectPose& now);
// Angle in degrees between the object's up axis now and initially.
double object_tilt_degrees(const ObjectPose& initial, const ObjectPose& now);

// Per-object outcomes relative to the initial poses: displacement (m), tilt (deg), toppled
// (tilt > 45 deg), lifted (lowest point above the table by > 2 cm now), in_bin, on_table.
nlohmann::json object_outcomes(const World& world, const std::vector<ObjectPose>& initial);

}  // namespace dojo::sim
