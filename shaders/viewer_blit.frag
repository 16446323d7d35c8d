#version 330
// The viewer window's blit: the renderer's linear radiance image, tone-mapped for display.
// Assembled by prt.runtime.viewer after tonemap.glsl (prt.shaders.assemble).
uniform sampler2D u_image;
uniform float u_exposure;
out vec4 f_color;
void main() {
    vec3 c = texelFetch(u_image, ivec2(gl_FragCoord.xy), 0).rgb;
    f_color = vec4(prt_tonemap(c, u_exposure), 1.0);
}
