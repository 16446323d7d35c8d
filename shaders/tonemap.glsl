// Tone mapping for display: the GLSL twin of prt.runtime.shading.tonemap().  Needs the #define
// PRT_TONEMAP_MAX, which prt.runtime.shading.GLSL_DEFINES gives from shading.TONEMAP_MAX (the one
// definition of the ceiling) when prt.shaders.assemble builds the program.

// Linear -> sRGB-encoded display value in [0, 1]: exposure, ACES filmic fit (Narkowicz 2015)
// per channel, then the sRGB OETF.  NaN and +-Inf become 0.  Twin of shading.tonemap().
vec3 prt_tonemap(vec3 radiance, float exposure) {
    vec3 x = radiance;
    for (int i = 0; i < 3; ++i) {
        if (isnan(x[i]) || isinf(x[i])) {
            x[i] = 0.0;
        }
    }
    // The curve is already 1 beyond ~7.3; the upper clamp keeps x * x finite.
    x = clamp(x * exposure, 0.0, PRT_TONEMAP_MAX);
    vec3 mapped = clamp((x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14), 0.0, 1.0);
    vec3 encoded = 1.055 * pow(mapped, vec3(1.0 / 2.4)) - 0.055;
    return mix(encoded, 12.92 * mapped, lessThanEqual(mapped, vec3(0.0031308)));
}
