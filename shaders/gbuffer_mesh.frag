#version 330
// G-buffer of a triangle mesh, fragment stage (runtime/gbuffer.py assembles it after
// segment_lookup.glsl, with that file's #defines).
//   attachment 0: position.xyz, covered (1)
//   attachment 1: unit normal facing the camera, segment id
// Deformable scenes (PRT_GBUFFER_REST): attachment 0 holds the rest position (what the networks and
// the segment rule take), attachment PRT_GBUFFER_WORLD the posed position (what shading takes).
// Back faces of closed surfaces are discarded here.  runtime/gbuffer.py also draws the closed
// faces apart with GL's culling on (nothing reaches the discard) and the two-sided ones, which
// must stay visible from both sides, in a second draw without it; one draw relies on this alone.

uniform vec3 u_eye;  // camera position, scene space

in vec3 v_position;
in vec3 v_normal;
flat in vec3 v_face_normal;
flat in ivec2 v_info;

layout(location = 0) out vec4 o_position;
layout(location = 1) out vec4 o_normal;
#ifdef PRT_GBUFFER_UV
in vec4 v_uv;
flat in float v_atlas;
layout(location = 2) out vec4 o_uv;  // u, v, atlas, covered: of the side facing the camera
#endif
#ifdef PRT_GBUFFER_REST
in vec3 v_rest;
layout(location = PRT_GBUFFER_WORLD) out vec4 o_world;  // posed position, covered
#endif
#ifdef PRT_GBUFFER_MATERIAL
// Scenes with per-object materials: albedo-texture u, v, object id, covered.
// PRT_GBUFFER_MATERIAL is the attachment's index (after the UV target when there is one).
in vec2 v_albedo_uv;
layout(location = PRT_GBUFFER_MATERIAL) out vec4 o_material;
#endif

#ifdef PRT_KNOWN_SEGMENT
// Triangles wholly in one k-d leaf: their segment comes with them (runtime/gbuffer.py draws the
// others with the descent per fragment, prt_segment).
flat in int v_segment;
#define PRT_SEGMENT_AT(p) v_segment
#else
#define PRT_SEGMENT_AT(p) prt_segment(v_info.x, p)
#endif

void main() {
    bool two_sided = v_info.y != 0;
    if (!two_sided && !gl_FrontFacing) {
        discard;
    }
    // The near plane keeps every fragment away from the eye, so to_eye is never zero.
    vec3 to_eye = normalize(u_eye - v_position);
    vec3 n = v_normal;
    if (!(dot(v_face_normal, v_face_normal) > 0.0) || !(dot(n, n) > 0.0)) {
        n = to_eye;  // degenerate face: any unit vector facing the camera
    } else if (two_sided && dot(v_face_normal, to_eye) < 0.0) {
        n = -n;  // the back side of an open surface: its smooth normal turns with it
    }
    if (dot(n, to_eye) < 0.0) {
        // Two-sided: show the side facing the camera.  Closed and front facing: only
        // rounding at grazing angles gets here, so drop the component pointing away.
        n = two_sided ? -n : n - dot(n, to_eye) * to_eye;
        if (!(dot(n, n) > 1e-12)) {
            n = to_eye;
        }
    }
    n = normalize(n);
#ifdef PRT_GBUFFER_REST
    o_position = vec4(v_rest, 1.0);
    o_normal = vec4(n, float(PRT_SEGMENT_AT(v_rest)));
    o_world = vec4(v_position, 1.0);
#else
    o_position = vec4(v_position, 1.0);
    o_normal = vec4(n, float(PRT_SEGMENT_AT(v_position)));
#endif
#ifdef PRT_GBUFFER_UV
    bool back = two_sided && dot(v_face_normal, to_eye) < 0.0;  // as the normal's flip above
    o_uv = vec4(back ? v_uv.zw : v_uv.xy, v_atlas, 1.0);
#endif
#ifdef PRT_GBUFFER_MATERIAL
    o_material = vec4(v_albedo_uv, float(v_info.x), 1.0);
#endif
}
