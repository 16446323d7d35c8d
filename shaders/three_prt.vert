// prt-three.js's material (export/web_page/prt-three.js), vertex stage: the G-buffer's vertex stage
// (gbuffer_mesh.vert) inside a THREE.ShaderMaterial.  three.js prepends its prefix (#version 300 es,
// precision, projectionMatrix, modelViewMatrix, the attributes position and normal): position is
// the scene-space corner (the networks' input), normal its smooth shading normal.
// The depth pre-pass (prt-three.js) draws the same positions: invariant, so that the material's
// fragments meet its depth exactly (LessEqual) and the networks run once per pixel.
invariant gl_Position;
in vec3 prt_face_normal;  // the face's unit normal (zero for a degenerate face)
in ivec2 prt_info;        // (object id, two-sided ? 1 : 0)
out vec3 v_position;
out vec3 v_normal;
flat out vec3 v_face_normal;
flat out ivec2 v_info;
#ifdef PRT_OBJECT_MATERIALS
in vec2 prt_albedo_uv;
out vec2 v_albedo_uv;
#endif

void main() {
    v_position = position;
    v_normal = normal;
    v_face_normal = prt_face_normal;
    v_info = prt_info;
#ifdef PRT_OBJECT_MATERIALS
    v_albedo_uv = prt_albedo_uv;
#endif
    gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0);
}
