// PCL's own VFH (pcl::VFHEstimation<PointXYZ, Normal, VFHSignature308>, the instantiation compiled
// into Debian's libpcl_features) on a cloud that benchmarks/vfh.py hands over, timed per call.
//
// usage: pcl_vfh INPUT.bin REPS NORMALIZE_DISTANCE SIZE_COMPONENT
//   INPUT.bin: int32 N, then N rows of float32 x y z nx ny nz (metres; unit normals).
// stdout: line 1 the per-call times in ms (feature only: the search tree is built once, outside
//         the timed calls, as VFH itself never searches); line 2 the per-call times in ms of a
//         compute() that builds its own kd-tree, as PCL's tutorial code does; line 3 the 308 bins.
#include <pcl/features/vfh.h>
#include <pcl/point_types.h>
#include <pcl/search/kdtree.h>

#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iostream>

namespace {

double ms_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 5) {
    std::cerr << "usage: pcl_vfh INPUT.bin REPS NORMALIZE_DISTANCE SIZE_COMPONENT\n";
    return 2;
  }
  std::ifstream in(argv[1], std::ios::binary);
  std::int32_t n = 0;
  in.read(reinterpret_cast<char*>(&n), sizeof n);
  if (!in || n < 2) {
    std::cerr << "pcl_vfh: " << argv[1] << " is not a cloud of at least 2 points\n";
    return 2;
  }
  pcl::PointCloud<pcl::PointXYZ>::Ptr points(new pcl::PointCloud<pcl::PointXYZ>);
  pcl::PointCloud<pcl::Normal>::Ptr normals(new pcl::PointCloud<pcl::Normal>);
  for (std::int32_t i = 0; i < n; ++i) {
    float r[6];
    in.read(reinterpret_cast<char*>(r), sizeof r);
    points->push_back(pcl::PointXYZ(r[0], r[1], r[2]));
    normals->push_back(pcl::Normal(r[3], r[4], r[5]));
  }
  if (!in) {
    std::cerr << "pcl_vfh: " << argv[1] << " ends before its " << n << " points\n";
    return 2;
  }
  const int reps = std::atoi(argv[2]);

  pcl::VFHEstimation<pcl::PointXYZ, pcl::Normal, pcl::VFHSignature308> vfh;
  vfh.setInputCloud(points);
  vfh.setInputNormals(normals);
  vfh.setNormalizeDistance(std::atoi(argv[3]) != 0);
  vfh.setFillSizeComponent(std::atoi(argv[4]) != 0);
  pcl::PointCloud<pcl::VFHSignature308> out;

  pcl::search::KdTree<pcl::PointXYZ>::Ptr tree(new pcl::search::KdTree<pcl::PointXYZ>(false));
  tree->setInputCloud(points);
  vfh.setSearchMethod(tree);
  vfh.compute(out);  // warm-up
  for (int k = 0; k < reps; ++k) {
    const auto t0 = std::chrono::steady_clock::now();
    vfh.compute(out);
    std::printf("%s%.6f", k ? " " : "", ms_since(t0));
  }
  std::printf("\n");
  for (int k = 0; k < reps; ++k) {
    pcl::VFHEstimation<pcl::PointXYZ, pcl::Normal, pcl::VFHSignature308> fresh;
    fresh.setInputCloud(points);
    fresh.setInputNormals(normals);
    fresh.setNormalizeDistance(std::atoi(argv[3]) != 0);
    fresh.setFillSizeComponent(std::atoi(argv[4]) != 0);
    const auto t0 = std::chrono::steady_clock::now();
    fresh.compute(out);
    std::printf("%s%.6f", k ? " " : "", ms_since(t0));
  }
  std::printf("\n");
  for (int b = 0; b < 308; ++b) std::printf("%s%.9g", b ? " " : "", out.points[0].histogram[b]);
  std::printf("\n");
  return 0;
}
