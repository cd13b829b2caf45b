#version 330
// Blit of the (possibly coarse) render; the sampler's bilinear filter upsamples it to the viewport.
uniform sampler2D rgb_tex;
in vec2 uv;
out vec4 color;
void main() { color = vec4(texture(rgb_tex, uv).rgb, 1.0); }
