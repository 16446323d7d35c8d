#version 330
// The viewer window's blit: the renderer's linear radiance image, tone-mapped for display.
// The image may be smaller than the window (dynamic resolution while the camera moves): it is
// sampled bilinearly in linear radiance, then tone-mapped.
// Assembled by prt.runtime.viewer after tonemap.glsl (prt.shaders.assemble).
uniform sampler2D u_image;
uniform vec2 u_window;  // window size in pixels
uniform float u_exposure;
out vec4 f_color;
void main() {
    vec3 c = texture(u_image, gl_FragCoord.xy / u_window).rgb;
    f_color = vec4(prt_tonemap(c, u_exposure), 1.0);
}
