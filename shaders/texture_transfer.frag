// Texture backend transfer pass (prt.runtime.backends.texture): the transfer of each covered
// pixel fetched bilinearly from the scene's transfer texture at the pixel's UV, written to the
// four RGBA32F targets the other backends fill (coefficients 4k .. 4k+3 in target k).
// With interreflection ("direct+rgb", 64 values per texel): PRT_TRANSFER_BLOCKS 16, written in
// two draws of 8 targets (u_part 0: blocks 0..7, 1: blocks 8..15), since OpenGL 3.3 guarantees
// 8 draw buffers.
#ifndef PRT_TRANSFER_BLOCKS
#define PRT_TRANSFER_BLOCKS 4
#endif
uniform sampler2D u_uv;             // G-buffer attachment 2: u, v, atlas, covered
uniform sampler2DArray u_transfer;  // layer BLOCKS * atlas + k: coefficients 4k .. 4k+3 (LINEAR, clamped)
layout(location = 0) out vec4 o_t0;
layout(location = 1) out vec4 o_t1;
layout(location = 2) out vec4 o_t2;
layout(location = 3) out vec4 o_t3;
#if PRT_TRANSFER_BLOCKS > 4
layout(location = 4) out vec4 o_t4;
layout(location = 5) out vec4 o_t5;
layout(location = 6) out vec4 o_t6;
layout(location = 7) out vec4 o_t7;
uniform int u_part;
#define PRT_TARGETS 8
#else
#define PRT_TARGETS 4
#endif

void main() {
    vec4 uv = texelFetch(u_uv, ivec2(gl_FragCoord.xy), 0);
    vec4 t[PRT_TARGETS];
    for (int k = 0; k < PRT_TARGETS; ++k) t[k] = vec4(0.0);
    if (uv.w >= 0.5) {
        float base = float(PRT_TRANSFER_BLOCKS) * floor(uv.z + 0.5);
#if PRT_TRANSFER_BLOCKS > 4
        base += float(PRT_TARGETS * u_part);
#endif
        for (int k = 0; k < PRT_TARGETS; ++k) {
            t[k] = texture(u_transfer, vec3(uv.xy, base + float(k)));
        }
    }
    o_t0 = t[0];
    o_t1 = t[1];
    o_t2 = t[2];
    o_t3 = t[3];
#if PRT_TRANSFER_BLOCKS > 4
    o_t4 = t[4];
    o_t5 = t[5];
    o_t6 = t[6];
    o_t7 = t[7];
#endif
}
