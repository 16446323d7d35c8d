// GLSL backend transfer pass: one fragment per pixel evaluates its segment's network (the
// paper's way) and writes the 16 coefficients to four RGBA32F targets.  Assembled by
// prt.runtime.backends.glsl with prt.shaders.assemble: sh_basis.glsl, then this file with its
// placeholders filled in: networks (the generated network functions: one per architecture in
// the compact form, after transfer_weights.glsl; one per segment in the older per-segment
// layouts) and dispatch (the statements choosing a segment's network: compact segments through
// u_segment_net / u_segment_base, per-segment ones through a switch over segment ids).

// With interreflection ("direct+rgb") the networks give 16 vec4 blocks (direct, indirect R, G,
// B): PRT_TRANSFER_BLOCKS 16.  OpenGL 3.3 guarantees 8 draw buffers, so there they are written in
// two draws of 8 targets (u_part 0: blocks 0..7, 1: blocks 8..15), each evaluating the networks.
// With PRT_ONE_PASS (GLSL 4.30: image load/store) one draw evaluates them once and writes blocks
// 0..7 to the 8 targets, blocks 8..15 by imageStore to the textures bound to image units 0..7.
// PRT_TRANSFER_TARGETS 4 (the web page, prt.export.web, where WebGL2 guarantees 4 draw buffers
// and SwiftShader offers 6): four draws of 4 targets, u_part 0..3 writing blocks 4 u_part ..
// 4 u_part + 3.

${networks}
#ifndef PRT_TRANSFER_BLOCKS
#define PRT_TRANSFER_BLOCKS 4
#endif
#ifndef PRT_TRANSFER_TARGETS
#define PRT_TRANSFER_TARGETS 8
#endif
uniform sampler2D u_position;  // xyz, covered
uniform sampler2D u_normal;    // xyz, segment
layout(location = 0) out vec4 o_t0;
layout(location = 1) out vec4 o_t1;
layout(location = 2) out vec4 o_t2;
layout(location = 3) out vec4 o_t3;
#if PRT_TRANSFER_BLOCKS > 4 && PRT_TRANSFER_TARGETS > 4
layout(location = 4) out vec4 o_t4;
layout(location = 5) out vec4 o_t5;
layout(location = 6) out vec4 o_t6;
layout(location = 7) out vec4 o_t7;
#endif
#if PRT_TRANSFER_BLOCKS > 4
#ifdef PRT_ONE_PASS
layout(rgba32f, binding = 0) uniform writeonly image2D u_i8;
layout(rgba32f, binding = 1) uniform writeonly image2D u_i9;
layout(rgba32f, binding = 2) uniform writeonly image2D u_i10;
layout(rgba32f, binding = 3) uniform writeonly image2D u_i11;
layout(rgba32f, binding = 4) uniform writeonly image2D u_i12;
layout(rgba32f, binding = 5) uniform writeonly image2D u_i13;
layout(rgba32f, binding = 6) uniform writeonly image2D u_i14;
layout(rgba32f, binding = 7) uniform writeonly image2D u_i15;
#else
uniform int u_part;
#endif
#endif
#ifdef PRT_SEGMENTS
uniform int u_segment_net[PRT_SEGMENTS];   // per segment id: its network function, -1 analytic, -2 per-segment GLSL
uniform int u_segment_base[PRT_SEGMENTS];  // its first texel in prt_weights
#endif
uniform vec4 u_analytic_scale[4];  // clamped-cosine band factor / pi of each coefficient

// Unshadowed transfer: the clamped cosine / pi turned to the normal (analytic segments; no
// interreflected light).
void prt_analytic_transfer(vec3 n, out vec4 t[PRT_TRANSFER_BLOCKS]) {
    vec4 y[4];
    prt_sh_basis(n, y);
    for (int k = 0; k < 4; ++k) t[k] = y[k] * u_analytic_scale[k];
    for (int k = 4; k < PRT_TRANSFER_BLOCKS; ++k) t[k] = vec4(0.0);
}

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    vec4 p = texelFetch(u_position, px, 0);
    vec4 ns = texelFetch(u_normal, px, 0);
    vec4 t[PRT_TRANSFER_BLOCKS];
    for (int k = 0; k < PRT_TRANSFER_BLOCKS; ++k) t[k] = vec4(0.0);
    if (p.w >= 0.5) {
        int segment = int(ns.w + 0.5);
${dispatch}
    }
#if PRT_TRANSFER_BLOCKS > 4 && PRT_TRANSFER_TARGETS == 4
    if (u_part == 0) {
        o_t0 = t[0]; o_t1 = t[1]; o_t2 = t[2]; o_t3 = t[3];
    } else if (u_part == 1) {
        o_t0 = t[4]; o_t1 = t[5]; o_t2 = t[6]; o_t3 = t[7];
    } else if (u_part == 2) {
        o_t0 = t[8]; o_t1 = t[9]; o_t2 = t[10]; o_t3 = t[11];
    } else {
        o_t0 = t[12]; o_t1 = t[13]; o_t2 = t[14]; o_t3 = t[15];
    }
#elif PRT_TRANSFER_BLOCKS > 4 && defined(PRT_ONE_PASS)
    o_t0 = t[0]; o_t1 = t[1]; o_t2 = t[2]; o_t3 = t[3]; o_t4 = t[4]; o_t5 = t[5]; o_t6 = t[6]; o_t7 = t[7];
    imageStore(u_i8, px, t[8]); imageStore(u_i9, px, t[9]); imageStore(u_i10, px, t[10]); imageStore(u_i11, px, t[11]);
    imageStore(u_i12, px, t[12]); imageStore(u_i13, px, t[13]); imageStore(u_i14, px, t[14]); imageStore(u_i15, px, t[15]);
#elif PRT_TRANSFER_BLOCKS > 4
    if (u_part == 0) {  // constant indices: a dynamic one makes Mesa spill t[] (minutes of compile)
        o_t0 = t[0]; o_t1 = t[1]; o_t2 = t[2]; o_t3 = t[3]; o_t4 = t[4]; o_t5 = t[5]; o_t6 = t[6]; o_t7 = t[7];
    } else {
        o_t0 = t[8]; o_t1 = t[9]; o_t2 = t[10]; o_t3 = t[11]; o_t4 = t[12]; o_t5 = t[13]; o_t6 = t[14]; o_t7 = t[15];
    }
#else
    o_t0 = t[0];
    o_t1 = t[1];
    o_t2 = t[2];
    o_t3 = t[3];
#endif
}
