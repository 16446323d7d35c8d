#version 330
// The vertex-space PRT baseline (prt.bench.vertex_prt): per-vertex transfer, interpolated by the rasteriser.
uniform mat4 u_view_projection;
in vec3 in_position;
in vec4 in_f0; in vec4 in_f1; in vec4 in_f2; in vec4 in_f3;  // transfer of the front side
in vec4 in_b0; in vec4 in_b1; in vec4 in_b2; in vec4 in_b3;  // of the back side (open surfaces)
in int in_two_sided;
out vec4 v_f0; out vec4 v_f1; out vec4 v_f2; out vec4 v_f3;
out vec4 v_b0; out vec4 v_b1; out vec4 v_b2; out vec4 v_b3;
flat out int v_two_sided;
void main() {
    v_f0 = in_f0; v_f1 = in_f1; v_f2 = in_f2; v_f3 = in_f3;
    v_b0 = in_b0; v_b1 = in_b1; v_b2 = in_b2; v_b3 = in_b3;
    v_two_sided = in_two_sided;
    gl_Position = u_view_projection * vec4(in_position, 1.0);
}
