#version 330
// A texture's region onto the bound framebuffer, opaque: the viewport's picture and the panel's cached pixels go
// under or between imgui's windows without blending. uv (0,0)-(1,1) spans the target rect (GL's bottom-left first).
uniform sampler2D picture;
uniform vec2 src_origin;  // the texture coordinate at the rect's bottom-left corner
uniform vec2 src_size;    // ... and the step to its top-right (negative y flips an image stored top row first)
in vec2 uv;
out vec4 color;
void main() { color = vec4(texture(picture, src_origin + uv * src_size).rgb, 1.0); }
