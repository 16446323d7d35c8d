// Counting the shade pass's broken-transfer marks without reading the frame back: this pass
// keeps only the texels whose alpha is above 1.5 (shade_pass.frag writes 2 where the transfer
// is NaN or Inf) and an occlusion query around it counts them (prt.runtime.gl.FlagCounter).
uniform sampler2D u_frame;
out vec4 f_flag;

void main() {
    if (!(texelFetch(u_frame, ivec2(gl_FragCoord.xy), 0).a > 1.5)) discard;
    f_flag = vec4(1.0);
}
