#version 330
// Cosine similarity to the selection query as a heatmap: -1..1 mapped through turbo; the threshold drawn as a contour.
#include "colormap.glsl"
uniform sampler2D sim_tex;
uniform float threshold;
in vec2 uv;
out vec4 color;
void main() {
    float s = texture(sim_tex, uv).r;
    vec3 c = turbo(s * 0.5 + 0.5);
    float edge = fwidth(s);
    float line = 1.0 - smoothstep(0.0, 1.5 * edge, abs(s - threshold));
    color = vec4(mix(c, vec3(1.0), line), 1.0);
}
