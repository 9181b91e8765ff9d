// 2D simplex noise (Gustavson 2005), double precision so that both backends and the Python
// reference (pbf_cuda/noise.py) agree to rounding; drives the ground heating pattern of eq. 5.
#pragma once
#include "common.h"

namespace pbf {

// Ken Perlin's reference permutation.
#define PBF_NOISE_PERMUTATION {151, 160, 137, 91, 90, 15, 131, 13, 201, 95, 96, 53, 194, 233, 7, 225, 140, 36, 103, 30, 69, 142, \
        8, 99, 37, 240, 21, 10, 23, 190, 6, 148, 247, 120, 234, 75, 0, 26, 197, 62, 94, 252, 219, 203, 117, \
        35, 11, 32, 57, 177, 33, 88, 237, 149, 56, 87, 174, 20, 125, 136, 171, 168, 68, 175, 74, 165, 71, \
        134, 139, 48, 27, 166, 77, 146, 158, 231, 83, 111, 229, 122, 60, 211, 133, 230, 220, 105, 92, 41, \
        55, 46, 245, 40, 244, 102, 143, 54, 65, 25, 63, 161, 1, 216, 80, 73, 209, 76, 132, 187, 208, 89, \
        18, 169, 200, 196, 135, 130, 116, 188, 159, 86, 164, 100, 109, 198, 173, 186, 3, 64, 52, 217, 226, \
        250, 124, 123, 5, 202, 38, 147, 118, 126, 255, 82, 85, 212, 207, 206, 59, 227, 47, 16, 58, 17, 182, \
        189, 28, 42, 223, 183, 170, 213, 119, 248, 152, 2, 44, 154, 163, 70, 221, 153, 101, 155, 167, 43, \
        172, 9, 129, 22, 39, 253, 19, 98, 108, 110, 79, 113, 224, 232, 178, 185, 112, 104, 218, 246, 97, \
        228, 251, 34, 242, 193, 238, 210, 144, 12, 191, 179, 162, 241, 81, 51, 145, 235, 249, 14, 239, \
        107, 49, 192, 214, 31, 181, 199, 106, 157, 184, 84, 204, 176, 115, 121, 50, 45, 127, 4, 150, 254, \
        138, 236, 205, 93, 222, 114, 67, 29, 24, 72, 243, 141, 128, 195, 78, 66, 215, 61, 156, 180}
#ifdef __CUDACC__
__constant__ unsigned char kNoisePermutationDevice[256] = PBF_NOISE_PERMUTATION;
#endif
static const unsigned char kNoisePermutationHost[256] = PBF_NOISE_PERMUTATION;

PBF_HD inline int noise_perm(int i) {
#ifdef __CUDA_ARCH__
    return kNoisePermutationDevice[i & 255];
#else
    return kNoisePermutationHost[i & 255];
#endif
}

PBF_HD inline double noise_corner(int gi, double x, double y) {
    double t = 0.5 - x * x - y * y;
    if (t < 0.0) return 0.0;
    // 2D gradients: the x, y components of Gustavson's 12 grad3 directions
    // gx = {1,-1,1,-1,1,-1,1,-1,0,0,0,0}, gy = {1,1,-1,-1,0,0,0,0,1,-1,1,-1}.
    int gx = gi < 8 ? ((gi & 1) ? -1 : 1) : 0;
    int gy = gi < 4 ? ((gi & 2) ? -1 : 1) : (gi < 8 ? 0 : ((gi & 1) ? -1 : 1));
    t *= t;
    return t * t * (gx * x + gy * y);
}

PBF_HD inline double simplex2(double xin, double yin) {
    const double F2 = 0.36602540378443864676;  // (sqrt(3) - 1) / 2
    const double G2 = 0.21132486540518711775;  // (3 - sqrt(3)) / 6
    double s = (xin + yin) * F2;
    double fi = floor(xin + s), fj = floor(yin + s);
    double t = (fi + fj) * G2;
    double x0 = xin - (fi - t), y0 = yin - (fj - t);
    int i1 = x0 > y0 ? 1 : 0, j1 = 1 - i1;
    double x1 = x0 - i1 + G2, y1 = y0 - j1 + G2;
    double x2 = x0 - 1.0 + 2.0 * G2, y2 = y0 - 1.0 + 2.0 * G2;
    int ii = static_cast<int>(static_cast<long long>(fi) & 255);
    int jj = static_cast<int>(static_cast<long long>(fj) & 255);
    int gi0 = noise_perm(ii + noise_perm(jj)) % 12;
    int gi1 = noise_perm(ii + i1 + noise_perm(jj + j1)) % 12;
    int gi2 = noise_perm(ii + 1 + noise_perm(jj + 1)) % 12;
    return 70.0 * (noise_corner(gi0, x0, y0) + noise_corner(gi1, x1, y1) + noise_corner(gi2, x2, y2));
}

}  // namespace pbf
