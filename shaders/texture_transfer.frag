// Texture backend transfer pass (prt.runtime.backends.texture): the transfer of each covered
// pixel fetched bilinearly from the scene's transfer texture at the pixel's UV, written to the
// four RGBA32F targets the other backends fill (coefficients 4k .. 4k+3 in target k).
uniform sampler2D u_uv;             // G-buffer attachment 2: u, v, atlas, covered
uniform sampler2DArray u_transfer;  // layer 4 * atlas + k: coefficients 4k .. 4k+3 (LINEAR, clamped)
layout(location = 0) out vec4 o_t0;
layout(location = 1) out vec4 o_t1;
layout(location = 2) out vec4 o_t2;
layout(location = 3) out vec4 o_t3;

void main() {
    vec4 uv = texelFetch(u_uv, ivec2(gl_FragCoord.xy), 0);
    vec4 t[4];
    t[0] = t[1] = t[2] = t[3] = vec4(0.0);
    if (uv.w >= 0.5) {
        float base = 4.0 * floor(uv.z + 0.5);
        for (int k = 0; k < 4; ++k) {
            t[k] = texture(u_transfer, vec3(uv.xy, base + float(k)));
        }
    }
    o_t0 = t[0];
    o_t1 = t[1];
    o_t2 = t[2];
    o_t3 = t[3];
}
