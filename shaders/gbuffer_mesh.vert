#version 330
// G-buffer of a triangle mesh, vertex stage.  The vertex buffer is unindexed: every corner
// carries its smooth shading normal, its triangle's geometric normal, object id and
// sidedness (the last three per face).

uniform mat4 u_view_projection;  // scene space -> clip space

in vec3 in_position;  // scene space
in vec3 in_normal;    // smooth shading normal of this corner (the face's normal across creases)
in vec3 in_face_normal;  // the face's unit normal (zero for a degenerate face)
in ivec2 in_info;     // (object id, two-sided ? 1 : 0)

out vec3 v_position;
out vec3 v_normal;
flat out vec3 v_face_normal;
flat out ivec2 v_info;
#ifdef PRT_GBUFFER_UV
in vec4 in_uv;      // UV of this corner in the transfer texture: front side .xy, back side .zw
in float in_atlas;  // the face's atlas (texture set)
out vec4 v_uv;
flat out float v_atlas;
#endif
#ifdef PRT_GBUFFER_REST
in vec3 in_rest;  // deformable scenes: this corner in the rest pose (the networks' position input)
out vec3 v_rest;
#endif
#ifdef PRT_KNOWN_SEGMENT
in int in_segment;  // the face's segment, where all of it lies in one k-d leaf (runtime/gbuffer.py)
flat out int v_segment;
#endif
#ifdef PRT_GBUFFER_MATERIAL
in vec2 in_albedo_uv;  // this corner's albedo-texture UV (the mesh's own; 0 without one)
out vec2 v_albedo_uv;
#endif

void main() {
    v_position = in_position;
    v_normal = in_normal;
    v_face_normal = in_face_normal;
    v_info = in_info;
#ifdef PRT_KNOWN_SEGMENT
    v_segment = in_segment;
#endif
#ifdef PRT_GBUFFER_REST
    v_rest = in_rest;
#endif
#ifdef PRT_GBUFFER_UV
    v_uv = in_uv;
    v_atlas = in_atlas;
#endif
#ifdef PRT_GBUFFER_MATERIAL
    v_albedo_uv = in_albedo_uv;
#endif
    gl_Position = u_view_projection * vec4(in_position, 1.0);
}
