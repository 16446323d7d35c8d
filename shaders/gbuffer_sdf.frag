#version 330
// G-buffer of an SDF scene: one full-screen pass (vertex stage fullscreen.vert) sphere
// traces the pixel's ray and writes the same targets as the mesh pass (gbuffer_mesh.frag).
// runtime/gbuffer.py assembles it (prt.shaders.assemble) after segment_lookup.glsl, with the
// #defines PRT_MAX_STEPS, PRT_HIT_EPS (hit threshold per unit of ray length), PRT_SCENE_BOX
// (half size of the box holding the scene) and those of segment_lookup.glsl, and with
// the placeholder scene_sdf filled with the scene's GLSL defining float scene_sdf(vec3 p).  The scene is object id 0;
// with PRT_SCENE_OBJECTS (mixed scenes) the GLSL also sets int prt_scene_object, the id of the nearest
// SDF object, read at the hit.  Mixed scenes draw this pass after their meshes, under the depth test.
// PRT_GBUFFER_MATERIAL (the material target's index): u, v (0), object id, covered.

${scene_sdf}

uniform vec3 u_eye;               // ray origin, scene space
uniform vec3 u_forward;           // unit view direction
uniform vec3 u_right;             // right * tan(fov_y / 2) * aspect: ray offset at ndc x = 1
uniform vec3 u_up;                // image up * tan(fov_y / 2): ray offset at ndc y = 1
uniform vec2 u_size;              // viewport size in pixels
uniform float u_near;             // clip distances along the view axis, as rasterisation
uniform float u_far;
uniform float u_pixel_angle;      // pixel footprint per unit distance: 2 tan(fov_y / 2) / height
uniform mat4 u_view_projection;   // for gl_FragDepth

layout(location = 0) out vec4 o_position;
layout(location = 1) out vec4 o_normal;
#ifdef PRT_GBUFFER_MATERIAL
layout(location = PRT_GBUFFER_MATERIAL) out vec4 o_material;
#endif

// Parameters (t_in, t_out) where the ray o + t d enters and leaves the box [-b, b]^3.
vec2 prt_ray_box(vec3 o, vec3 d, float b) {
    // Components of exactly zero would divide by zero; a tiny stand-in gives the same slabs.
    vec3 safe = mix(d, vec3(1e-20), lessThan(abs(d), vec3(1e-20)));
    vec3 t1 = (vec3(-b) - o) / safe;
    vec3 t2 = (vec3(b) - o) / safe;
    vec3 lo = min(t1, t2);
    vec3 hi = max(t1, t2);
    return vec2(max(max(lo.x, lo.y), lo.z), min(min(hi.x, hi.y), hi.z));
}

// Tap k of the tetrahedral difference (the gradient is the sum of tap * scene_sdf(p + tap * h)).
vec3 prt_tap(int k) {
    return k == 0 ? vec3(1.0, -1.0, -1.0) : k == 1 ? vec3(-1.0, -1.0, 1.0) : k == 2 ? vec3(-1.0, 1.0, -1.0) : vec3(1.0);
}

void main() {
    vec2 ndc = gl_FragCoord.xy / u_size * 2.0 - 1.0;
    vec3 rd = normalize(u_forward + ndc.x * u_right + ndc.y * u_up);
    // Clip like the rasteriser: view-axis depth in [near, far] is t * dot(rd, forward).
    float cos_axis = dot(rd, u_forward);
    vec2 box = prt_ray_box(u_eye, rd, PRT_SCENE_BOX);
    float t = max(box.x, u_near / cos_axis);
    float t_end = min(box.y, u_far / cos_axis);
    if (!(t <= t_end)) {
        discard;
    }

    // scene_sdf has ONE call site (compilers inline every call, and a neural SDF is large): the
    // loop marches the ray, then evaluates the 4 taps of the gradient at the hit.  A ray starting
    // inside the solid (camera inside it) passes through to its exit, as the mesh pass discards
    // the back faces of closed surfaces.  The loop runs at most PRT_MAX_STEPS + 4 times, far
    // below llvmpipe's cap on the loop iterations of an invocation (65535, all loops together).
    bool inside = false;
    bool hit = false;
    float dist = 0.0;
    int tap = -1;  // >= 0: evaluating gradient tap `tap` at p
    vec3 p = vec3(0.0);
    vec3 n = vec3(0.0);
    float h = 2e-4;
    int object_id = 0;
    for (int i = 0; i < PRT_MAX_STEPS + 4; ++i) {
        vec3 s = prt_tap(tap);
        float d = scene_sdf(tap < 0 ? u_eye + t * rd : p + s * h);
#ifdef PRT_SCENE_OBJECTS
        object_id = tap < 0 ? prt_scene_object : object_id;  // the object at the last march step
#endif
        if (tap >= 0) {
            n += s * d;
            if (++tap == 4) {
                break;
            }
            continue;
        }
        if (i == 0) {
            inside = d < 0.0;
        }
        dist = d;
        float eps = PRT_HIT_EPS * t;
        if (inside) {
            inside = dist <= eps;
            t += max(abs(dist), eps);
        } else if (dist < eps) {
            hit = true;
        } else {
            t += dist;
        }
        if (!hit && (t > t_end || i == PRT_MAX_STEPS - 1)) {
            // Out of steps (grazing rays creep along a surface): a hit if within the pixel's cone.
            if (t > t_end || inside || !(dist < u_pixel_angle * t)) {
                break;
            }
            hit = true;
        }
        if (hit) {
            p = u_eye + t * rd;
            h = max(2e-4, PRT_HIT_EPS * t);
            tap = 0;
        }
    }
    if (!hit) {
        discard;
    }

    vec3 to_eye = -rd;
    if (!(dot(n, n) > 1e-30)) {
        n = to_eye;  // flat spot of the field: any unit vector facing the camera
    }
    n = normalize(n);
    if (dot(n, to_eye) < 0.0) {
        // Only grazing hits get here: drop the component pointing away from the camera.
        n -= dot(n, to_eye) * to_eye;
        n = dot(n, n) > 1e-12 ? normalize(n) : to_eye;
    }

    vec4 clip = u_view_projection * vec4(p, 1.0);
    gl_FragDepth = clamp(0.5 * clip.z / clip.w + 0.5, 0.0, 1.0);
    o_position = vec4(p, 1.0);
    o_normal = vec4(n, float(prt_segment(object_id, p)));
#ifdef PRT_GBUFFER_MATERIAL
    o_material = vec4(0.0, 0.0, float(object_id), 1.0);
#endif
}
