// pybind11 bindings of the C++ core: argument checks and buffer plumbing only; the work is in the
// stage headers (distance.h, sign.h, farfield.h, dag.h, sdf.h), which mirror the Python stage files.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <stdexcept>
#include <string>

#include "sdf.h"

namespace py = pybind11;

namespace {

template <class T>
using Array = py::array_t<T, py::array::c_style | py::array::forcecast>;

void require(bool ok, const std::string& msg) {
  if (!ok) throw std::invalid_argument(msg);
}

void check_corners(const Array<double>& a, const char* name) {
  require(a.ndim() == 3 && a.shape(1) == 3 && a.shape(2) == 3, std::string(name) + " must be (T, 3, 3) float64");
}

void check_resolution(int64_t r) {
  require(r >= navi::kBrickCells && r <= 4096 && (r & (r - 1)) == 0, "resolution must be a power of two in [8, 4096]");
}

py::tuple signed_field(const Array<double>& drawn, const Array<uint8_t>& face_class, const Array<double>& barrier,
                       const Array<double>& seeds, int64_t resolution, float band, int threads) {
  check_corners(drawn, "drawn");
  check_corners(barrier, "barrier");
  check_resolution(resolution);
  require(face_class.ndim() == 1 && face_class.shape(0) == drawn.shape(0), "face_class must be (F,) uint8");
  require(seeds.ndim() == 2 && seeds.shape(1) == 3, "seeds must be (S, 3) float64");
  require(band > 0.0f, "band must be positive");
  const int64_t n = resolution + 1, nb = resolution / navi::kBrickCells;
  Array<float> lattice({n, n, n});
  Array<uint8_t> classes({nb, nb, nb});
  navi::SdfStats stats;
  {
    py::gil_scoped_release release;
    stats = navi::signed_field(drawn.data(), drawn.shape(0), face_class.data(), barrier.data(), barrier.shape(0),
                               seeds.data(), seeds.shape(0), resolution, band, threads, lattice.mutable_data(),
                               classes.mutable_data());
  }
  py::dict seconds;
  for (const auto& [stage, t] : stats.seconds) seconds[py::str(stage)] = t;
  return py::make_tuple(lattice, classes, stats.flags, stats.seeds_used, stats.wall_points, stats.free_points,
                        seconds);
}

py::tuple build_dag(const Array<float>& lattice, const Array<uint8_t>& brick_class, float band, float quant_step,
                    int threads) {
  require(lattice.ndim() == 3 && lattice.shape(0) == lattice.shape(1) && lattice.shape(1) == lattice.shape(2),
          "lattice must be (R+1, R+1, R+1) float32");
  const int64_t r = lattice.shape(0) - 1;
  check_resolution(r);
  const int64_t nb = r / navi::kBrickCells;
  require(brick_class.ndim() == 3 && brick_class.shape(0) == nb && brick_class.shape(1) == nb &&
              brick_class.shape(2) == nb,
          "brick_class must be (R/8, R/8, R/8) uint8");
  navi::DagOut out;
  {
    py::gil_scoped_release release;
    out = navi::build_dag(r, lattice.data(), brick_class.data(), band, quant_step, threads);
  }
  const int64_t nodes = static_cast<int64_t>(out.nodes.size() / 8);
  const int64_t bricks = static_cast<int64_t>(out.classes.size());
  Array<uint32_t> node_arr({nodes, int64_t{8}});
  Array<int8_t> brick_arr({bricks, int64_t{navi::kBrickSamples}});
  Array<uint8_t> class_arr({bricks});
  std::copy(out.nodes.begin(), out.nodes.end(), node_arr.mutable_data());
  std::copy(out.bricks.begin(), out.bricks.end(), brick_arr.mutable_data());
  std::copy(out.classes.begin(), out.classes.end(), class_arr.mutable_data());
  return py::make_tuple(out.root, out.levels, node_arr, brick_arr, class_arr);
}

py::tuple nearest(const Array<double>& corners, int64_t resolution, double reach, int threads) {
  check_corners(corners, "corners");
  check_resolution(resolution);
  const int64_t n = resolution + 1;
  Array<float> dist({n, n, n});
  Array<int32_t> tri({n, n, n});
  {
    py::gil_scoped_release release;
    const navi::Triangles t = navi::make_triangles(corners.data(), corners.shape(0));
    const navi::Buckets b = navi::bucket_triangles(t, resolution / navi::kBrickCells, reach);
    navi::nearest_triangles(t, b, resolution, reach, threads, dist.mutable_data(), tri.mutable_data());
  }
  return py::make_tuple(dist, tri);
}

Array<int32_t> squared_edt(const Array<uint8_t>& sites, int threads) {
  require(sites.ndim() == 3 && sites.shape(0) == sites.shape(1) && sites.shape(1) == sites.shape(2),
          "sites must be (n, n, n) uint8");
  const int64_t n = sites.shape(0);
  Array<int32_t> out({n, n, n});
  {
    py::gil_scoped_release release;
    navi::squared_edt(n - 1, sites.data(), threads, out.mutable_data());
  }
  return out;
}

uint32_t murmur3_32(const py::bytes& data, uint32_t seed) {
  const std::string s = data;
  return navi::murmur3_32(reinterpret_cast<const uint8_t*>(s.data()), s.size(), seed);
}

}  // namespace

PYBIND11_MODULE(_core, m) {
  m.doc() = "Navi compiler C++17 core (twin of the NumPy reference stages)";
  m.def("signed_field", &signed_field, py::arg("drawn"), py::arg("face_class"), py::arg("barrier"), py::arg("seeds"),
        py::arg("resolution"), py::arg("band"), py::arg("threads") = 0,
        "Triangles in voxels -> (lattice, brick_class, flags, seeds_used, wall_points, free_points, seconds)");
  m.def("build_dag", &build_dag, py::arg("lattice"), py::arg("brick_class"), py::arg("band"), py::arg("quant_step"),
        py::arg("threads") = 0, "Signed lattice -> (root, levels, nodes, bricks, brick_class)");
  m.def("nearest", &nearest, py::arg("corners"), py::arg("resolution"), py::arg("reach"), py::arg("threads") = 0,
        "Exact distances within reach: (distance float32, triangle int32)");
  m.def("squared_edt", &squared_edt, py::arg("sites"), py::arg("threads") = 0, "Exact squared EDT (int32)");
  m.def("murmur3_32", &murmur3_32, py::arg("data"), py::arg("seed") = 0, "MurmurHash3 x86_32");
}
