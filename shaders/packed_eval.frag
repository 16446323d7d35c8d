#version 330
// Evaluation over packed inputs (prt.runtime.gl.run_fragment_program): one fragment per input
// row, the row's values in texel (x, y) of u_input.  The placeholder below (body) takes the
// caller's source: a void main() writing f_out, plus any functions it needs.
uniform sampler2D u_input;
out vec4 f_out;
vec4 prt_input() { return texelFetch(u_input, ivec2(gl_FragCoord.xy), 0); }

${body}
