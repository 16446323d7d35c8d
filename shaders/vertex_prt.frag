#version 330
// The vertex-space PRT baseline: the interpolated transfer of the visible side into 4 RGBA32F targets.
in vec4 v_f0; in vec4 v_f1; in vec4 v_f2; in vec4 v_f3;
in vec4 v_b0; in vec4 v_b1; in vec4 v_b2; in vec4 v_b3;
flat in int v_two_sided;
layout(location = 0) out vec4 o_t0;
layout(location = 1) out vec4 o_t1;
layout(location = 2) out vec4 o_t2;
layout(location = 3) out vec4 o_t3;
void main() {
    // The G-buffer's rule: back faces of closed surfaces are hidden, open ones show their back.
    if (v_two_sided == 0 && !gl_FrontFacing) discard;
    bool back = !gl_FrontFacing;
    o_t0 = back ? v_b0 : v_f0;
    o_t1 = back ? v_b1 : v_f1;
    o_t2 = back ? v_b2 : v_f2;
    o_t3 = back ? v_b3 : v_f3;
}
