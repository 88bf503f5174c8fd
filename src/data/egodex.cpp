#include "data/egodex.h"

#include <hdf5.h>
#include <torch/torch.h>

#include <algorithm>
#include <mutex>

#include "core/error.h"
#include "io/video.h"

namespace fs = std::filesystem;

namespace dojo::data {

namespace {

// Debian's libhdf5 is built without thread safety: every call goes through this lock.
std::mutex& hdf5_mutex() {
  static std::mutex m;
  return m;
}

// An open HDF5 file; errors name the file. Caller holds hdf5_mutex().
class H5 {
 public:
  explicit H5(const fs::path& path) : path_(path.string()) {
    H5Eset_auto2(H5E_DEFAULT, nullptr, nullptr);  // errors become dojo::Error, not stderr noise
    file_ = H5Fopen(path_.c_str(), H5F_ACC_RDONLY, H5P_DEFAULT);
    if (file_ < 0) throw Error(path_ + ": cannot open as HDF5");
  }
  ~H5() { H5Fclose(file_); }
  H5(const H5&) = delete;
  H5& operator=(const H5&) = delete;

  bool exists(const std::string& name) const {
    // H5Lexists needs every parent to exist: check the path one component at a time.
    std::string partial;
    size_t pos = 0;
    while (pos != std::string::npos) {
      pos = name.find('/', pos + 1);
      partial = name.substr(0, pos);
      if (partial.empty() || partial == "/") continue;
      if (H5Lexists(file_, partial.c_str(), H5P_DEFAULT) <= 0) return false;
    }
    return true;
  }

  std::vector<int64_t> shape(const std::string& name) const {
    const hid_t ds = open_dataset(name);
    const hid_t space = H5Dget_space(ds);
    const int rank = H5Sget_simple_extent_ndims(space);
    std::vector<hsize_t> dims(static_cast<size_t>(std::max(rank, 0)));
    if (rank > 0) H5Sget_simple_extent_dims(space, dims.data(), nullptr);
    H5Sclose(space);
    H5Dclose(ds);
    return std::vector<int64_t>(dims.begin(), dims.end());
  }

  at::Tensor read_f32(const std::string& name) const {
    const auto dims = shape(name);
    auto out = torch::empty(dims, torch::kFloat32);
    const hid_t ds = open_dataset(name);
    const herr_t status = H5Dread(ds, H5T_NATIVE_FLOAT, H5S_ALL, H5S_ALL, H5P_DEFAULT, out.data_ptr<float>());
    H5Dclose(ds);
    if (status < 0) throw Error(path_ + ": cannot read '" + name + "' as float");
    return out;
  }

  std::vector<std::string> children(const std::string& group) const {
    std::vector<std::string> names;
    if (!exists(group)) return names;
    const hid_t g = H5Gopen2(file_, group.c_str(), H5P_DEFAULT);
    if (g < 0) return names;
    H5G_info_t info;
    if (H5Gget_info(g, &info) >= 0)
      for (hsize_t i = 0; i < info.nlinks; ++i) {
        const ssize_t n = H5Lget_name_by_idx(g, ".", H5_INDEX_NAME, H5_ITER_INC, i, nullptr, 0, H5P_DEFAULT);
        if (n <= 0) continue;
        std::string name(static_cast<size_t>(n) + 1, '\0');
        H5Lget_name_by_idx(g, ".", H5_INDEX_NAME, H5_ITER_INC, i, name.data(), name.size(), H5P_DEFAULT);
        name.resize(static_cast<size_t>(n));
        names.push_back(name);
      }
    H5Gclose(g);
    return names;
  }

  // A string attribute of the root group ("" when absent or not a string).
  std::string root_string_attribute(const std::string& name) const {
    if (H5Aexists(file_, name.c_str()) <= 0) return "";
    const hid_t attr = H5Aopen(file_, name.c_str(), H5P_DEFAULT);
    const hid_t type = H5Aget_type(attr);
    std::string out;
    if (H5Tget_class(type) == H5T_STRING) {
      const hid_t mem = H5Tcopy(H5T_C_S1);
      if (H5Tis_variable_str(type) > 0) {
        H5Tset_size(mem, H5T_VARIABLE);
        char* value = nullptr;
        if (H5Aread(attr, mem, &value) >= 0 && value) {
          out = value;
          H5free_memory(value);
        }
      } else {
        const size_t size = H5Tget_size(type);
        H5Tset_size(mem, size);
        std::string buffer(size, '\0');
        if (H5Aread(attr, mem, buffer.data()) >= 0) out = buffer.c_str();
      }
      H5Tclose(mem);
    }
    H5Tclose(type);
    H5Aclose(attr);
    return out;
  }

 private:
  hid_t open_dataset(const std::string& name) const {
    if (!exists(name)) throw Error(path_ + ": no dataset '" + name + "'");
    const hid_t ds = H5Dopen2(file_, name.c_str(), H5P_DEFAULT);
    if (ds < 0) throw Error(path_ + ": cannot open dataset '" + name + "'");
    return ds;
  }

  std::string path_;
  hid_t file_ = -1;
};

// Frame count of an EgoDex file: the length of the camera transforms (else any joint's).
int64_t frame_count(const H5& h5, const fs::path& path) {
  const auto joints = h5.children("/transforms");
  if (joints.empty()) throw Error(path.string() + ": no /transforms group (not an EgoDex file)");
  const std::string joint =
      std::find(joints.begin(), joints.end(), kEgoDexCamera) != joints.end() ? kEgoDexCamera : joints.front();
  const auto dims = h5.shape("/transforms/" + joint);
  if (dims.size() != 3 || dims[1] != 4 || dims[2] != 4)
    throw Error(path.string() + ": /transforms/" + joint + " is not [N, 4, 4]");
  return dims[0];
}

}  // namespace

bool looks_like_egodex(const fs::path& dir) {
  std::error_code ec;
  for (auto it = fs::recursive_directory_iterator(dir, ec); !ec && it != fs::recursive_directory_iterator();
       it.increment(ec)) {
    if (!it->is_regular_file() || it->path().extension() != ".hdf5") continue;
    fs::path mp4 = it->path();
    mp4.replace_extension(".mp4");
    if (fs::exists(mp4)) return true;
  }
  return false;
}

std::shared_ptr<EgoDexDataset> EgoDexDataset::open(const fs::path& root) {
  auto ds = std::shared_ptr<EgoDexDataset>(new EgoDexDataset());
  ds->root_ = root;
  std::vector<fs::path> files;
  for (const auto& e : fs::recursive_directory_iterator(root))
    if (e.is_regular_file() && e.path().extension() == ".hdf5") files.push_back(e.path());
  std::sort(files.begin(), files.end());
  if (files.empty()) throw Error(root.string() + ": no .hdf5 files (not an EgoDex tree)");
  DatasetInfo& info = ds->info_;
  info.name = dataset_name(root);
  info.embodiment = Embodiment::kHuman;
  info.fps = 30;  // EgoDex records at 30 Hz
  for (const auto& path : files) {
    Episode ep;
    ep.hdf5 = path;
    ep.video = path;
    ep.video.replace_extension(".mp4");
    if (!fs::exists(ep.video))
      throw Error(ep.video.string() + ": video file missing (paired with " + path.filename().string() + ")");
    {
      std::lock_guard<std::mutex> lock(hdf5_mutex());
      const H5 h5(path);
      ep.frames = frame_count(h5, path);
      ep.description = h5.root_string_attribute("llm_description");
      ep.task = h5.root_string_attribute("task");
    }
    if (ep.task.empty()) ep.task = path.parent_path().filename().string();
    EpisodeEntry entry;
    entry.id = fs::relative(path, root).replace_extension("").string();
    entry.frames = ep.frames;
    entry.split = "train";
    entry.task = ep.description.empty() ? ep.task : ep.description;
    info.episodes.push_back(entry);
    ds->episodes_.push_back(std::move(ep));
  }
  const auto first = io::probe_video(ds->episodes_.front().video.string());
  info.height = first.height;
  info.width = first.width;
  if (first.fps > 0) info.fps = first.fps;
  return ds;
}

at::Tensor EgoDexDataset::read_transforms(size_t index, const std::string& joint) const {
  const Episode& ep = episodes_.at(index);
  std::lock_guard<std::mutex> lock(hdf5_mutex());
  const H5 h5(ep.hdf5);
  auto t = h5.read_f32("/transforms/" + joint);  // [N, 4, 4]
  if (t.dim() != 3 || t.size(0) != ep.frames || t.size(1) != 4 || t.size(2) != 4)
    throw Error(ep.hdf5.string() + ": /transforms/" + joint + " is not [" + std::to_string(ep.frames) +
                ", 4, 4]");
  return t;
}

at::Tensor EgoDexDataset::read_intrinsic(size_t index) const {
  const Episode& ep = episodes_.at(index);
  std::lock_guard<std::mutex> lock(hdf5_mutex());
  const H5 h5(ep.hdf5);
  auto k = h5.read_f32("/camera/intrinsic");
  if (k.sizes() != at::IntArrayRef({3, 3}))
    throw Error(ep.hdf5.string() + ": /camera/intrinsic is not [3, 3]");
  return k;
}

std::vector<std::string> EgoDexDataset::joints(size_t index) const {
  std::lock_guard<std::mutex> lock(hdf5_mutex());
  const H5 h5(episodes_.at(index).hdf5);
  return h5.children("/transforms");
}

EpisodeData EgoDexDataset::read_arrays(size_t index) const {
  const Episode& ep = episodes_.at(index);
  EpisodeData d;
  const auto camera = read_transforms(index, kEgoDexCamera);  // [N, 4, 4] camera -> world
  std::vector<at::Tensor> wrists;
  for (const char* hand : {kEgoDexLeftHand, kEgoDexRightHand}) {
    const auto h = read_transforms(index, hand);  // [N, 4, 4] hand -> world
    // Camera-frame position: R_c^T (p_h - t_c).
    const auto rotation = camera.slice(1, 0, 3).slice(2, 0, 3);                                // [N, 3, 3]
    const auto offset = (h.slice(1, 0, 3).select(2, 3) - camera.slice(1, 0, 3).select(2, 3));  // [N, 3]
    wrists.push_back(torch::bmm(rotation.transpose(1, 2), offset.unsqueeze(2)).squeeze(2));    // [N, 3]
  }
  d.hidden_motion = torch::cat(wrists, 1).contiguous();  // [N, 6]
  if (!torch::isfinite(d.hidden_motion).all().item<bool>())
    throw Error(ep.hdf5.string() + ": hand transforms contain NaN or Inf");
  const auto k = read_intrinsic(index);
  d.meta["description"] = ep.description;
  d.meta["task"] = ep.task;
  d.meta["intrinsic"] = {{k[0][0].item<float>(), k[0][1].item<float>(), k[0][2].item<float>()},
                         {k[1][0].item<float>(), k[1][1].item<float>(), k[1][2].item<float>()},
                         {k[2][0].item<float>(), k[2][1].item<float>(), k[2][2].item<float>()}};
  return d;
}

at::Tensor EgoDexDataset::read_frames(size_t index, const std::vector<int64_t>& frames) const {
  const Episode& ep = episodes_.at(index);
  io::VideoReaderOptions options;
  options.threads = 1;  // the loader's parallelism comes from its workers
  io::VideoReader reader(ep.video.string(), options);
  for (int64_t f : frames)
    if (f < 0 || f >= ep.frames || f >= reader.num_frames())
      throw Error(ep.video.string() + ": frame " + std::to_string(f) + " outside the video (" +
                  std::to_string(reader.num_frames()) + " frames, " + std::to_string(ep.frames) +
                  " HDF5 rows)");
  return reader.read_frames(frames);  // [N, H, W, 3] u8
}

nlohmann::json EgoDexDataset::describe() const {
  nlohmann::json j = EpisodeSource::describe();
  j["cameras"] = {"egocentric"};
  j["hidden_motion"] = "left and right wrist xyz in the camera frame (6-d)";
  if (!episodes_.empty()) j["joints"] = joints(0);
  return j;
}

}  // namespace dojo::data
