// Shading pass of the GLSL backend: one fragment per pixel reads the G-buffer and the pixel's
// transfer (four (W, H) RGBA32F textures written by the transfer pass), then shades with
// prt_shade (shading.glsl).  Assembled by prt.runtime.renderer with prt.shaders.assemble:
// the files of prt.runtime.shading.GLSL_FILES (with its GLSL_DEFINES), then this file.
uniform sampler2D u_position;  // xyz, covered
uniform sampler2D u_normal;    // xyz, segment
uniform vec3 u_eye;
#ifdef PRT_TRANSFER_ARRAY
// The web page (prt.export.web): block k of the transfer is layer k of one array texture (WebGL2
// may offer only 16 texture units, fewer than 16 blocks + the G-buffer + the materials need).
uniform sampler2DArray u_transfer;
#define PRT_T(k, name) texelFetch(u_transfer, ivec3(px, k), 0)
#else
uniform sampler2D u_t0;
uniform sampler2D u_t1;
uniform sampler2D u_t2;
uniform sampler2D u_t3;
#define PRT_T(k, name) texelFetch(name, px, 0)
#endif
out vec4 f_color;
#if defined(PRT_INTERREFLECTION) && !defined(PRT_TRANSFER_ARRAY)
// Interreflection ("direct+rgb"): the indirect transfer of R, G, B, coefficients 4k .. 4k+3 of
// channel c in u_t{4 + 4c + k} (the GLSL backend's second set of targets, or the CPU's upload).
uniform sampler2D u_t4, u_t5, u_t6, u_t7, u_t8, u_t9, u_t10, u_t11, u_t12, u_t13, u_t14, u_t15;
#endif
#ifdef PRT_OBJECT_MATERIALS
// Per-object materials (runtime/materials.py): the G-buffer's material target (u, v, object id,
// covered) and the table, one column per object id: row 0 albedo.rgb + kind, row 1
// specular.rgb, row 2 the Phong lobe's band factors Lambda_0..3, row 3 the albedo texture
// (layer or -1, width, height) in u_albedo_textures (linear RGB, row 0 = top of the image).
uniform sampler2D u_gbuffer_material;
uniform sampler2D u_material_table;
uniform sampler2DArray u_albedo_textures;

// Bilinear, wrapping lookup: the twin of prt.runtime.albedo_textures.sample_bilinear.
vec3 prt_albedo_texel(vec2 uv, vec4 info) {
    int layer = int(info.x + 0.5);
    ivec2 size = ivec2(info.yz + 0.5);
    float x = uv.x * float(size.x) - 0.5;
    float y = (1.0 - uv.y) * float(size.y) - 0.5;
    float x0 = floor(x), y0 = floor(y);
    float fx = x - x0, fy = y - y0;
    int ix0 = int(x0), iy0 = int(y0);
    int ix1 = ix0 + 1, iy1 = iy0 + 1;
    ix0 = ((ix0 % size.x) + size.x) % size.x;  // GLSL's % may be negative for negative operands
    iy0 = ((iy0 % size.y) + size.y) % size.y;
    ix1 = ((ix1 % size.x) + size.x) % size.x;
    iy1 = ((iy1 % size.y) + size.y) % size.y;
    vec3 top = texelFetch(u_albedo_textures, ivec3(ix0, iy0, layer), 0).rgb * (1.0 - fx)
             + texelFetch(u_albedo_textures, ivec3(ix1, iy0, layer), 0).rgb * fx;
    vec3 bottom = texelFetch(u_albedo_textures, ivec3(ix0, iy1, layer), 0).rgb * (1.0 - fx)
                + texelFetch(u_albedo_textures, ivec3(ix1, iy1, layer), 0).rgb * fx;
    return top * (1.0 - fy) + bottom * fy;
}

vec3 prt_shade_pixel(vec4 t[4], vec3 n, vec3 v, ivec2 px, vec3 indirect) {
    vec4 gm = texelFetch(u_gbuffer_material, px, 0);
    int object_id = int(gm.z + 0.5);
    vec4 albedo_kind = texelFetch(u_material_table, ivec2(object_id, 0), 0);
    vec4 texture_info = texelFetch(u_material_table, ivec2(object_id, 3), 0);
    if (texture_info.x > -0.5) {
        albedo_kind.rgb *= prt_albedo_texel(gm.xy, texture_info);
    }
    vec3 specular = texelFetch(u_material_table, ivec2(object_id, 1), 0).rgb;
    vec4 band = texelFetch(u_material_table, ivec2(object_id, 2), 0);
    // Coefficient i of band l: i = 0 | 1..3 | 4..8 | 9..15.
    vec4 lobe[4];
    lobe[0] = vec4(band.x, band.y, band.y, band.y);
    lobe[1] = vec4(band.z);
    lobe[2] = vec4(band.z, band.w, band.w, band.w);
    lobe[3] = vec4(band.w);
    return prt_shade_with_indirect(t, n, v, albedo_kind.rgb, specular, lobe, int(albedo_kind.w + 0.5), indirect);
}
#else
vec3 prt_shade_pixel(vec4 t[4], vec3 n, vec3 v, ivec2 px, vec3 indirect) {
    return prt_shade_with_indirect(t, n, v, u_albedo, u_specular, u_lobe, u_material_kind, indirect);
}
#endif

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    vec4 p = texelFetch(u_position, px, 0);
    if (p.w < 0.5) {
        f_color = vec4(0.0);
        return;
    }
    vec3 n = texelFetch(u_normal, px, 0).xyz;
    vec4 t[4];
    t[0] = PRT_T(0, u_t0);
    t[1] = PRT_T(1, u_t1);
    t[2] = PRT_T(2, u_t2);
    t[3] = PRT_T(3, u_t3);
    // Alpha 2 marks a transfer that is NaN or Inf (a broken network): shading would clamp it to
    // black, so the renderer reads the flag and refuses the frame.
    bool broken = false;
    for (int k = 0; k < 4; ++k) broken = broken || any(isnan(t[k])) || any(isinf(t[k]));
    vec3 indirect = vec3(0.0);
#ifdef PRT_INTERREFLECTION
    vec4 tr[4], tg[4], tb[4];
    tr[0] = PRT_T(4, u_t4); tr[1] = PRT_T(5, u_t5); tr[2] = PRT_T(6, u_t6); tr[3] = PRT_T(7, u_t7);
    tg[0] = PRT_T(8, u_t8); tg[1] = PRT_T(9, u_t9); tg[2] = PRT_T(10, u_t10); tg[3] = PRT_T(11, u_t11);
    tb[0] = PRT_T(12, u_t12); tb[1] = PRT_T(13, u_t13); tb[2] = PRT_T(14, u_t14); tb[3] = PRT_T(15, u_t15);
    for (int k = 0; k < 4; ++k) {
        broken = broken || any(isnan(tr[k])) || any(isinf(tr[k])) || any(isnan(tg[k])) || any(isinf(tg[k]))
                 || any(isnan(tb[k])) || any(isinf(tb[k]));
    }
    indirect = prt_incident_rgb(tr, tg, tb);
#endif
    f_color = vec4(prt_shade_pixel(t, n, u_eye - p.xyz, px, indirect), broken ? 2.0 : 1.0);
}
