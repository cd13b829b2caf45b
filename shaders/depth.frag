#version 330
// z-depth through the turbo colormap between near and far; zero opacity shows as dark grey.
#include "colormap.glsl"
uniform sampler2D depth_tex;
uniform float near;
uniform float far;
in vec2 uv;
out vec4 color;
void main() {
    float z = texture(depth_tex, uv).r;
    float t = (z - near) / max(far - near, 1e-6);
    color = vec4(z > 0.0 ? turbo(1.0 - t) : vec3(0.15), 1.0);
}
