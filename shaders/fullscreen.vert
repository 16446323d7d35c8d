#version 330
// Full-screen triangle from gl_VertexID alone, so no vertex buffer is needed.  PRT_FULLSCREEN_Z
// (NDC depth, default 0) lets a pass sit at the far plane (1): with a depth test "<=" against a
// G-buffer's depth it then shades only the pixels no geometry covers (runtime/background.py).
#ifndef PRT_FULLSCREEN_Z
#define PRT_FULLSCREEN_Z 0.0
#endif
void main() {
    vec2 v = vec2(float((gl_VertexID & 1) << 2) - 1.0, float((gl_VertexID & 2) << 1) - 1.0);
    gl_Position = vec4(v, PRT_FULLSCREEN_Z, 1.0);
}
