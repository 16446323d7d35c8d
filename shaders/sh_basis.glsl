// Real spherical harmonics for 4 bands (16 functions), the GLSL twin of prt.runtime.sh.basis.
// Conventions as in runtime/sh.py: orthonormal real SH, flat index i = l*(l+1) + m, polar axis
// +z, no Condon-Shortley phase.  Coefficient i lives in sh[i / 4][i % 4].
// No #version line: include by concatenation after the shader's own header.

// Evaluate Y_0 .. Y_15 at direction d (normalised here; a zero vector counts as +z, as in numpy).
void prt_sh_basis(vec3 d, out vec4 sh[4]) {
    float len2 = dot(d, d);
    vec3 u = len2 > 0.0 ? d * inversesqrt(len2) : vec3(0.0, 0.0, 1.0);
    float x = u.x;
    float y = u.y;
    float z = u.z;
    float x2 = x * x;
    float y2 = y * y;
    float z2 = z * z;

    // l = 0 and l = 1: Y_00, Y_1-1 = c*y, Y_10 = c*z, Y_11 = c*x.
    sh[0] = vec4(0.28209479177387814, 0.4886025119029199 * y, 0.4886025119029199 * z,
                 0.4886025119029199 * x);
    // l = 2, m = -2 .. 1.
    sh[1] = vec4(1.0925484305920792 * x * y, 1.0925484305920792 * y * z,
                 0.31539156525252005 * (3.0 * z2 - 1.0), 1.0925484305920792 * x * z);
    // l = 2, m = 2; then l = 3, m = -3 .. -1.
    sh[2] = vec4(0.5462742152960396 * (x2 - y2), 0.5900435899266435 * y * (3.0 * x2 - y2),
                 2.890611442640554 * x * y * z, 0.4570457994644658 * y * (5.0 * z2 - 1.0));
    // l = 3, m = 0 .. 3.
    sh[3] = vec4(0.3731763325901154 * z * (5.0 * z2 - 3.0), 0.4570457994644658 * x * (5.0 * z2 - 1.0),
                 1.445305721320277 * z * (x2 - y2), 0.5900435899266435 * x * (x2 - 3.0 * y2));
}
