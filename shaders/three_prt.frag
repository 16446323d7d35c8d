// prt-three.js's material (export/web_page/prt-three.js), fragment stage: the web page's G-buffer,
// transfer and shade passes in one forward fragment.  Assembled by prt.export.web_assets after
// sh_basis.glsl, segment_lookup.glsl and shading.glsl, with the scene's network GLSL (the same
// fills as transfer_pass.frag); three.js prepends its prefix and resolves the two #include lines
// at the end (the renderer's tone mapping and output colour space, as for its own materials).
//
// Everything is in the scene's own frame (the object's local space): the networks take the
// scene-space position and normal; u_eye is the camera in that frame and u_light the light turned
// into it (prt-three.js, from the object's world rotation and the light's rotation about +Y).
// The output is linear radiance times u_exposure; three.js tone-maps it.

${networks}
#ifndef PRT_TRANSFER_BLOCKS
#define PRT_TRANSFER_BLOCKS 4
#endif
#ifdef PRT_SEGMENTS
uniform int u_segment_net[PRT_SEGMENTS];   // per segment id: its network function, -1 analytic
uniform int u_segment_base[PRT_SEGMENTS];  // its first texel in prt_weights
#endif
uniform vec4 u_analytic_scale[4];  // clamped-cosine band factor / pi of each coefficient
uniform vec3 u_eye;                // the camera, scene space
uniform float u_exposure;          // a scale of this material's radiance (before three's tone mapping)

in vec3 v_position;
in vec3 v_normal;
flat in vec3 v_face_normal;
flat in ivec2 v_info;

// Twin of transfer_pass.frag's: the clamped cosine / pi turned to the normal.
void prt_analytic_transfer(vec3 n, out vec4 t[PRT_TRANSFER_BLOCKS]) {
    vec4 y[4];
    prt_sh_basis(n, y);
    for (int k = 0; k < 4; ++k) t[k] = y[k] * u_analytic_scale[k];
    for (int k = 4; k < PRT_TRANSFER_BLOCKS; ++k) t[k] = vec4(0.0);
}

#ifdef PRT_OBJECT_MATERIALS
// Per-object materials: the table (one column per object id; shade_pass.frag's layout) and the
// albedo textures.
uniform sampler2D u_material_table;
uniform sampler2DArray u_albedo_textures;
in vec2 v_albedo_uv;

// Twin of shade_pass.frag's prt_albedo_texel (bilinear, wrapping).
vec3 prt_albedo_texel(vec2 uv, vec4 info) {
    int layer = int(info.x + 0.5);
    ivec2 size = ivec2(info.yz + 0.5);
    float x = uv.x * float(size.x) - 0.5;
    float y = (1.0 - uv.y) * float(size.y) - 0.5;
    float x0 = floor(x), y0 = floor(y);
    float fx = x - x0, fy = y - y0;
    int ix0 = int(x0), iy0 = int(y0);
    int ix1 = ix0 + 1, iy1 = iy0 + 1;
    ix0 = ((ix0 % size.x) + size.x) % size.x;
    iy0 = ((iy0 % size.y) + size.y) % size.y;
    ix1 = ((ix1 % size.x) + size.x) % size.x;
    iy1 = ((iy1 % size.y) + size.y) % size.y;
    vec3 top = texelFetch(u_albedo_textures, ivec3(ix0, iy0, layer), 0).rgb * (1.0 - fx)
             + texelFetch(u_albedo_textures, ivec3(ix1, iy0, layer), 0).rgb * fx;
    vec3 bottom = texelFetch(u_albedo_textures, ivec3(ix0, iy1, layer), 0).rgb * (1.0 - fx)
                + texelFetch(u_albedo_textures, ivec3(ix1, iy1, layer), 0).rgb * fx;
    return top * (1.0 - fy) + bottom * fy;
}

vec3 prt_shade_fragment(vec4 t[4], vec3 n, vec3 v, vec3 indirect) {
    int object_id = v_info.x;
    vec4 albedo_kind = texelFetch(u_material_table, ivec2(object_id, 0), 0);
    vec4 texture_info = texelFetch(u_material_table, ivec2(object_id, 3), 0);
    if (texture_info.x > -0.5) {
        albedo_kind.rgb *= prt_albedo_texel(v_albedo_uv, texture_info);
    }
    vec3 specular = texelFetch(u_material_table, ivec2(object_id, 1), 0).rgb;
    vec4 band = texelFetch(u_material_table, ivec2(object_id, 2), 0);
    vec4 lobe[4];
    lobe[0] = vec4(band.x, band.y, band.y, band.y);
    lobe[1] = vec4(band.z);
    lobe[2] = vec4(band.z, band.w, band.w, band.w);
    lobe[3] = vec4(band.w);
    return prt_shade_with_indirect(t, n, v, albedo_kind.rgb, specular, lobe, int(albedo_kind.w + 0.5), indirect);
}
#else
vec3 prt_shade_fragment(vec4 t[4], vec3 n, vec3 v, vec3 indirect) {
    return prt_shade_with_indirect(t, n, v, u_albedo, u_specular, u_lobe, u_material_kind, indirect);
}
#endif

void main() {
    // The G-buffer's normal (twin of gbuffer_mesh.frag): facing the camera.  Closed faces are drawn
    // with three's back-face culling (FrontSide), two-sided ones without (DoubleSide).
    bool two_sided = v_info.y != 0;
    vec3 to_eye = normalize(u_eye - v_position);
    vec3 n = v_normal;
    if (!(dot(v_face_normal, v_face_normal) > 0.0) || !(dot(n, n) > 0.0)) {
        n = to_eye;
    } else if (two_sided && dot(v_face_normal, to_eye) < 0.0) {
        n = -n;
    }
    if (dot(n, to_eye) < 0.0) {
        n = two_sided ? -n : n - dot(n, to_eye) * to_eye;
        if (!(dot(n, n) > 1e-12)) {
            n = to_eye;
        }
    }
    n = normalize(n);
    int segment = prt_segment(v_info.x, v_position);
    // The transfer pass (the dispatch reads p, ns, segment and writes t).
    vec4 p = vec4(v_position, 1.0);
    vec4 ns = vec4(n, float(segment));
    vec4 t[PRT_TRANSFER_BLOCKS];
    for (int k = 0; k < PRT_TRANSFER_BLOCKS; ++k) t[k] = vec4(0.0);
    {
${dispatch}
    }
    // The shade pass.
    vec4 direct[4];
    direct[0] = t[0]; direct[1] = t[1]; direct[2] = t[2]; direct[3] = t[3];
    vec3 indirect = vec3(0.0);
#if PRT_TRANSFER_BLOCKS > 4
    vec4 tr[4], tg[4], tb[4];
    tr[0] = t[4]; tr[1] = t[5]; tr[2] = t[6]; tr[3] = t[7];
    tg[0] = t[8]; tg[1] = t[9]; tg[2] = t[10]; tg[3] = t[11];
    tb[0] = t[12]; tb[1] = t[13]; tb[2] = t[14]; tb[3] = t[15];
    indirect = prt_incident_rgb(tr, tg, tb);
#endif
    vec3 radiance = prt_shade_fragment(direct, n, u_eye - v_position, indirect);
    gl_FragColor = vec4(radiance * u_exposure, 1.0);
    #include <tonemapping_fragment>
    #include <colorspace_fragment>
}
