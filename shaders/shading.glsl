// PRT shading for 4 SH bands: the GLSL twin of prt.runtime.shading (see that module's
// docstring for the definitions).  Assembled after sh_basis.glsl by prt.shaders.assemble (no
// #version line here).  Every uniform is produced by prt.runtime.shading.shader_uniforms().
//
// Layouts (coefficient i of a 16-vector lives in component i % 4 of element i / 4):
//   u_light[i]          L[i, :], the (rotated) RGB lighting coefficients.
//   u_light_matrix[b]   b = 16*c + 4*bi + bj holds the 4x4 block M_c[4*bi .. 4*bi+3, 4*bj .. 4*bj+3]
//                       of the light matrix of channel c (0 = R, 1 = G, 2 = B), uploaded
//                       column-major, so u_light_matrix[b] * v multiplies that block by v.
//   u_lobe[i / 4][i % 4] Lambda_l(i): Phong-lobe band factor of coefficient i's band.
//   u_material_kind     PRT_MATERIAL_DIFFUSE or PRT_MATERIAL_GLOSSY.
// Uniform storage: 48 mat4 + 16 vec3 + 4 vec4 + 2 vec3 + 1 int, about 860 components (a vec3
// may take a vec4 slot) of the 1024 fragment uniform components OpenGL 3.3 guarantees.

uniform vec3 u_light[16];
uniform mat4 u_light_matrix[48];
uniform vec4 u_lobe[4];
uniform vec3 u_albedo;
uniform vec3 u_specular;
uniform int u_material_kind;

const int PRT_MATERIAL_DIFFUSE = 0;
const int PRT_MATERIAL_GLOSSY = 1;
const float PRT_PI = 3.14159265358979323846;

// v / |v|, or 0 for a zero vector (numpy's twin does the same instead of producing NaN).
vec3 prt_unit(vec3 v) {
    float len2 = dot(v, v);
    return len2 > 0.0 ? v * inversesqrt(len2) : vec3(0.0);
}

// dot(T_c, L_c) per channel of three transfer vectors (the indirect R, G, B transfer of
// interreflection, "direct+rgb" layout).
vec3 prt_incident_rgb(vec4 tr[4], vec4 tg[4], vec4 tb[4]) {
    vec3 incident = vec3(0.0);
    for (int i = 0; i < 4; ++i) {
        for (int j = 0; j < 4; ++j) {
            vec3 l = u_light[4 * i + j];
            incident += vec3(tr[i][j] * l.r, tg[i][j] * l.g, tb[i][j] * l.b);
        }
    }
    return incident;
}

// Outgoing radiance (linear RGB, >= 0) for transfer vector t, normal n and direction v from
// the point towards the eye (n and v need not be unit length), with the material given
// (a pixel's own, runtime/materials.py) rather than the uniform one.  indirect: the
// interreflected light dot(T_ind_c, L_c) (prt_incident_rgb; 0 without interreflection), added
// as a diffuse term scaled by the albedo, also on glossy receivers (their lobe sees the direct
// light only: the approximation stated in prt.runtime.shading).
vec3 prt_shade_with_indirect(vec4 t[4], vec3 n, vec3 v, vec3 albedo, vec3 specular, vec4 lobe[4], int kind, vec3 indirect) {
    // Diffuse: dot(T, L_c) per channel.
    vec3 incident = indirect;
    for (int i = 0; i < 4; ++i) {
        incident += t[i].x * u_light[4 * i] + t[i].y * u_light[4 * i + 1]
                  + t[i].z * u_light[4 * i + 2] + t[i].w * u_light[4 * i + 3];
    }
    vec3 radiance = albedo * incident;

    if (kind == PRT_MATERIAL_GLOSSY) {
        // Phong lobe about the mirror direction, evaluated as lobe-scaled basis at r.
        vec3 r = reflect(-prt_unit(v), prt_unit(n));
        vec4 lobe_at_r[4];
        prt_sh_basis(r, lobe_at_r);
        for (int i = 0; i < 4; ++i) {
            lobe_at_r[i] *= lobe[i];
        }
        // spec_c = pi * sum_k lobe_at_r[k] * (M_c t)_k, one 4-row slice of M_c t at a time.
        vec3 spec = vec3(0.0);
        for (int c = 0; c < 3; ++c) {
            for (int bi = 0; bi < 4; ++bi) {
                int row = 16 * c + 4 * bi;
                vec4 transferred = u_light_matrix[row] * t[0] + u_light_matrix[row + 1] * t[1]
                                 + u_light_matrix[row + 2] * t[2] + u_light_matrix[row + 3] * t[3];
                spec[c] += dot(lobe_at_r[bi], transferred);
            }
        }
        radiance += specular * (PRT_PI * spec);
    }
    // Four SH bands ring below zero near strong lights; negative radiance is not meaningful.
    return max(radiance, vec3(0.0));
}

// prt_shade_with_indirect without interreflected light.
vec3 prt_shade_with(vec4 t[4], vec3 n, vec3 v, vec3 albedo, vec3 specular, vec4 lobe[4], int kind) {
    return prt_shade_with_indirect(t, n, v, albedo, specular, lobe, kind, vec3(0.0));
}

// prt_shade_with the uniform material (u_albedo, u_specular, u_lobe, u_material_kind).
vec3 prt_shade(vec4 t[4], vec3 n, vec3 v) {
    return prt_shade_with(t, n, v, u_albedo, u_specular, u_lobe, u_material_kind);
}
