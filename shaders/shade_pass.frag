// Shading pass: one fragment per pixel reads the G-buffer and the pixel's transfer, then shades
// with prt_shade (shading.glsl).  Assembled by prt.runtime.renderer: "#version 330", the
// defines below, sh_basis.glsl, shading.glsl, then this file.
//
// PRT_TRANSFER_WIDE: transfer in one (4W, H) texture, pixel (x, y) at texels 4x..4x+3 of row
//   H-1-y (the ONNX backend uploads its top-first CPU image as is);
// otherwise: four (W, H) textures in GL order (the GLSL backend's transfer pass writes them).
uniform sampler2D u_position;  // xyz, covered
uniform sampler2D u_normal;    // xyz, segment
uniform vec3 u_eye;
#ifdef PRT_TRANSFER_WIDE
uniform sampler2D u_transfer;
#else
uniform sampler2D u_t0;
uniform sampler2D u_t1;
uniform sampler2D u_t2;
uniform sampler2D u_t3;
#endif
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
#ifdef PRT_TRANSFER_WIDE
    ivec2 base = ivec2(4 * px.x, textureSize(u_normal, 0).y - 1 - px.y);
    for (int k = 0; k < 4; ++k) t[k] = texelFetch(u_transfer, base + ivec2(k, 0), 0);
#else
    t[0] = texelFetch(u_t0, px, 0);
    t[1] = texelFetch(u_t1, px, 0);
    t[2] = texelFetch(u_t2, px, 0);
    t[3] = texelFetch(u_t3, px, 0);
#endif
    f_color = vec4(prt_shade(t, n, u_eye - p.xyz), 1.0);
}
