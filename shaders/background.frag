// The environment map drawn where no geometry is: one fragment per pixel turns its camera ray
// into equirectangular coordinates (prt.runtime.sh.direction_to_equirect_uv's convention:
// u = 0.5 at -Z, 0.75 at +X; v = 0 at +Y) and samples the map, linear radiance out.
uniform sampler2D u_envmap;     // row 0 (v = 0) is +Y
uniform mat3 u_to_map;          // world direction -> the map's frame (inverse of the light's rotation)
uniform vec3 u_forward;
uniform vec3 u_right;
uniform vec3 u_up;
uniform vec2 u_half;            // tan(fov/2) * (aspect, 1)
uniform vec2 u_size;            // framebuffer size in pixels
out vec4 f_color;

const float PI = 3.14159265358979;

void main() {
    // GL's row order (row 0 at the bottom), as the G-buffer's depth this pass is tested against;
    // the read-back is flipped.  u_size.y - gl_FragCoord.y is the image row from the top + 0.5.
    vec2 ndc = vec2(gl_FragCoord.x / u_size.x * 2.0 - 1.0, 1.0 - (u_size.y - gl_FragCoord.y) / u_size.y * 2.0);
    vec3 d = normalize(u_to_map * (u_forward + ndc.x * u_half.x * u_right + ndc.y * u_half.y * u_up));
    float u = fract(atan(d.x, -d.z) / (2.0 * PI) + 0.5);
    float v = acos(clamp(d.y, -1.0, 1.0)) / PI;
    f_color = vec4(textureLod(u_envmap, vec2(u, v), 0.0).rgb, 1.0);
}
