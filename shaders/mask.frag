#version 330
// Mask overlay on RGB: pixels whose map value (the similarity where the selection's region reaches) is above the
// threshold (a uniform: the slider costs one draw) are tinted.
uniform sampler2D rgb_tex;
uniform sampler2D sim_tex;
uniform float threshold;
uniform vec3 tint;
uniform float strength;
in vec2 uv;
out vec4 color;
void main() {
    vec3 c = texture(rgb_tex, uv).rgb;
    float s = texture(sim_tex, uv).r;
    float inside = step(threshold, s);
    color = vec4(mix(c, tint, inside * strength), 1.0);
}
