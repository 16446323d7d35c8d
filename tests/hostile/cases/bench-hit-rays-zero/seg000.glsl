// seg0_transfer: a constant transfer, the GLSL twin of the corpus's linear network.
void seg0_transfer(vec3 position, vec3 normal, out vec4 t[4]) {
    t[0] = vec4(0.6, 0.05, 0.05, 0.05);
    t[1] = vec4(0.05);
    t[2] = vec4(0.05);
    t[3] = vec4(0.05);
}
