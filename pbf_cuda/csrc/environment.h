// The environment profile T0(y) of section 4: the temperature of the air at rest, against which buoyancy
// (eq. 6), the smoothing's anomaly (eq. 12-17), the density shift and the relaxation (C2) are measured.
// The paper's profile is linear, T0(y) = T_g - Gamma y. A capping inversion (docs/validation.md, "Shallow
// cumulus") makes it piecewise linear and continuous:
//   T0(y) = T_g - Gamma y                                   y <= z_i
//         = T0(z_i) + dT (y - z_i) / delta                  z_i < y <= z_i + delta   (the inversion layer)
//         = T0(z_i) + dT - Gamma_a (y - z_i - delta)        above
// with z_i = inversion_height (0: no inversion, the paper's profile), delta = inversion_depth,
// dT = inversion_strength and Gamma_a = lapse_rate_above. The local lapse Gamma(y) = -dT0/dy sets the
// buoyancy frequency N^2 = k_b (Gamma_d - Gamma(y)) / T0(y).
// Python twin: pbf_cuda/environment.py (tests/test_environment.py checks that the two agree).
#pragma once
#include "common.h"

namespace pbf {

struct EnvironmentProfile {
    float ground_temperature;   // T_g, K
    float lapse_rate;           // Gamma below the inversion, K/m
    float inversion_height;     // z_i, m; 0: no inversion
    float inversion_depth;      // delta, m (> 0)
    float inversion_strength;   // dT, K
    float lapse_rate_above;     // Gamma_a, K/m

    PBF_HD bool has_inversion() const { return inversion_height > 0.0f; }
    // T0(y), K.
    PBF_HD float temperature(float y) const {
        if (!has_inversion() || y <= inversion_height) return ground_temperature - lapse_rate * y;
        float base = ground_temperature - lapse_rate * inversion_height;
        float above = y - inversion_height;
        if (above <= inversion_depth) return base + inversion_strength * (above / inversion_depth);
        return base + inversion_strength - lapse_rate_above * (above - inversion_depth);
    }
    // Gamma(y) = -dT0/dy, K/m (the value of the segment that holds y; at a kink, the lower one).
    PBF_HD float lapse(float y) const {
        if (!has_inversion() || y <= inversion_height) return lapse_rate;
        if (y <= inversion_height + inversion_depth) return -inversion_strength / inversion_depth;
        return lapse_rate_above;
    }
    // How far y is through the inversion layer: 0 below it (and without an inversion), 1 above it.
    PBF_HD float inversion_fraction(float y) const {
        if (!has_inversion() || y <= inversion_height) return 0.0f;
        float f = (y - inversion_height) / inversion_depth;
        return f < 1.0f ? f : 1.0f;
    }
    // T0(y_i) - T0(y_i - dy), K: the environment's change over a rise dy that ends at y_i. Linear profile:
    // -Gamma dy exactly as the paper's form computes it.
    PBF_HD float change(float y_i, float dy) const {
        if (!has_inversion()) return -lapse_rate * dy;
        return temperature(y_i) - temperature(y_i - dy);
    }
};

}  // namespace pbf
