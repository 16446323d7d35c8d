// Shading pass of the GLSL backend: one fragment per pixel reads the G-buffer and the pixel's
// transfer (four (W, H) RGBA32F textures written by the transfer pass), then shades with
// prt_shade (shading.glsl).  Assembled by prt.runtime.renderer with prt.shaders.assemble:
// the files of prt.runtime.shading.GLSL_FILES (with its GLSL_DEFINES), then this file.
uniform sampler2D u_position;  // xyz, covered
uniform sampler2D u_normal;    // xyz, segment
uniform vec3 u_eye;
uniform sampler2D u_t0;
uniform sampler2D u_t1;
uniform sampler2D u_t2;
uniform sampler2D u_t3;
out vec4 f_color;

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    vec4 p = texelFetch(u_position, px, 0);
    if (p.w < 0.5) {
        f_color = vec4(0.0);
        return;
    }
    vec3 n = texelFetch(u_normal, px, 0).xyz;
    vec4 t[4];
    t[0] = texelFetch(u_t0, px, 0);
    t[1] = texelFetch(u_t1, px, 0);
    t[2] = texelFetch(u_t2, px, 0);
    t[3] = texelFetch(u_t3, px, 0);
    // Alpha 2 marks a transfer that is NaN or Inf (a broken network): shading would clamp it to
    // black, so the renderer reads the flag and refuses the frame.
    bool broken = false;
    for (int k = 0; k < 4; ++k) broken = broken || any(isnan(t[k])) || any(isinf(t[k]));
    f_color = vec4(prt_shade(t, n, u_eye - p.xyz), broken ? 2.0 : 1.0);
}
