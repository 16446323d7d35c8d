// GLSL backend transfer pass: one fragment per pixel evaluates its segment's network (the
// paper's way) and writes the 16 coefficients to four RGBA32F targets.  Assembled by
// prt.runtime.backends.glsl with prt.shaders.assemble: sh_basis.glsl, then this file with its
// placeholders filled in: networks (each segment's generated network function) and dispatch
// (a switch over segment ids).

${networks}
uniform sampler2D u_position;  // xyz, covered
uniform sampler2D u_normal;    // xyz, segment
layout(location = 0) out vec4 o_t0;
layout(location = 1) out vec4 o_t1;
layout(location = 2) out vec4 o_t2;
layout(location = 3) out vec4 o_t3;
uniform vec4 u_analytic_scale[4];  // clamped-cosine band factor / pi of each coefficient

// Unshadowed transfer: the clamped cosine / pi turned to the normal (analytic segments).
void prt_analytic_transfer(vec3 n, out vec4 t[4]) {
    vec4 y[4];
    prt_sh_basis(n, y);
    for (int k = 0; k < 4; ++k) t[k] = y[k] * u_analytic_scale[k];
}

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    vec4 p = texelFetch(u_position, px, 0);
    vec4 ns = texelFetch(u_normal, px, 0);
    vec4 t[4];
    t[0] = t[1] = t[2] = t[3] = vec4(0.0);
    if (p.w >= 0.5) {
        int segment = int(ns.w + 0.5);
        switch (segment) {
${dispatch}
        }
    }
    o_t0 = t[0];
    o_t1 = t[1];
    o_t2 = t[2];
    o_t3 = t[3];
}
