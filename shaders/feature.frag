#version 330
// Feature map projected on its first three principal components (done on the worker), scaled to [0, 1].
uniform sampler2D feature_tex;
uniform vec3 lo;
uniform vec3 hi;
in vec2 uv;
out vec4 color;
void main() {
    vec3 f = texture(feature_tex, uv).rgb;
    color = vec4(clamp((f - lo) / max(hi - lo, vec3(1e-6)), 0.0, 1.0), 1.0);
}
