#version 330
// Prepended to fragment sources evaluated over packed inputs (runtime.gl.run_fragment_program):
// one fragment per input row, the row's values in texel (x, y) of u_input.
uniform sampler2D u_input;
out vec4 f_out;
vec4 prt_input() { return texelFetch(u_input, ivec2(gl_FragCoord.xy), 0); }
