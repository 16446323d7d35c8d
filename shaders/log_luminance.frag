#version 330
// Auto exposure on the GPU (prt.runtime.exposure_gl): each fragment of a small target sums
// log(EPS + L) over one PRT_BLOCK x PRT_BLOCK tile of the frame, L the Rec. 709 luminance of the
// linear radiance, over the pixels the G-buffer covers (depth < 1), and counts those pixels.
// With PRT_COVERED_BY_ALPHA (the web page, which reduces the shade pass's output before the
// background is drawn) a pixel is covered where the frame's alpha is above 0.5 (shade_pass.frag
// writes 0 where nothing is drawn, 1 on geometry).
// The CPU adds the tiles up (float64) and finishes prt.runtime.exposure.exposure_from_log_mean:
// the numpy twin is prt.runtime.exposure.log_average_luminance.
uniform sampler2D u_frame;  // RGBA32F linear radiance (the renderer's frame texture)
uniform sampler2D u_depth;  // the G-buffer's depth: 1 where nothing was drawn (unused with PRT_COVERED_BY_ALPHA)
uniform ivec2 u_size;       // the frame's size in pixels
out vec4 f_sum;             // (sum of log(EPS + L), covered pixels, 0, 0) of the tile

void main() {
    ivec2 base = ivec2(gl_FragCoord.xy) * PRT_BLOCK;
    float s = 0.0;
    float n = 0.0;
    for (int y = 0; y < PRT_BLOCK; ++y) {
        for (int x = 0; x < PRT_BLOCK; ++x) {
            ivec2 p = base + ivec2(x, y);
            if (p.x >= u_size.x || p.y >= u_size.y) continue;
            vec4 c4 = texelFetch(u_frame, p, 0);
#ifdef PRT_COVERED_BY_ALPHA
            if (!(c4.a > 0.5)) continue;
#else
            if (texelFetch(u_depth, p, 0).r >= 1.0) continue;
#endif
            vec3 c = c4.rgb;
            float lum = dot(c, vec3(PRT_LUM_R, PRT_LUM_G, PRT_LUM_B));
            // negative and non-finite luminance count as 0, as in the numpy twin
            if (!(lum > 0.0) || isinf(lum)) lum = 0.0;
            s += log(PRT_EPS + lum);
            n += 1.0;
        }
    }
    f_sum = vec4(s, n, 0.0, 0.0);
}
