// The scene's one weight texture (compact GLSL, prt.export.glsl_compact): every network
// segment's texels (a header, then its tensors or grid tables) one after another, texel i at
// (i % PRT_WEIGHTS_WIDTH, i / PRT_WEIGHTS_WIDTH).  A segment's shared network function reads
// its own texels from the base texel the dispatch passes it.
#ifndef PRT_WEIGHTS_WIDTH
#define PRT_WEIGHTS_WIDTH 1024
#endif
uniform sampler2D prt_weights;

vec4 prt_weight(int i) { return texelFetch(prt_weights, ivec2(i % PRT_WEIGHTS_WIDTH, i / PRT_WEIGHTS_WIDTH), 0); }
