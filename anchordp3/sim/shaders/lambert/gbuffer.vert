#version 450
// anchordp3's one-pass camera shader, vertex stage: view-space position and normal per vertex.

layout(set = 0, binding = 0) uniform CameraBuffer {
  mat4 viewMatrix;
  mat4 projectionMatrix;
  mat4 viewMatrixInverse;
  mat4 projectionMatrixInverse;
  float width;
  float height;
} camera;

layout(set = 1, binding = 0) uniform ObjectTransformBuffer {
  mat4 modelMatrix;
} object;

layout(set = 1, binding = 1) uniform ObjectDataBuffer {
  uvec4 segmentation;
  float transparency;
  int shadeFlat;
} objectData;

layout(location = 0) in vec3 position;
layout(location = 1) in vec3 normal;
layout(location = 2) in vec2 uv;
layout(location = 3) in vec3 tangent;    // unused; declared so that every pack in a process reads
layout(location = 4) in vec3 bitangent;  // the same vertex layout as SAPIEN's own packs

layout(location = 0) out vec4 outViewPosition;
layout(location = 1) out vec3 outViewNormal;
layout(location = 2) out vec2 outUV;
layout(location = 3) out flat uvec4 outSegmentation;

void main() {
  mat4 modelView = camera.viewMatrix * object.modelMatrix;
  outViewPosition = modelView * vec4(position, 1.0);
  // normals follow the inverse transpose: primitives are scaled unevenly (a box is a scaled cube)
  outViewNormal = transpose(inverse(mat3(modelView))) * normal;
  outUV = uv;
  outSegmentation = objectData.segmentation;
  gl_Position = camera.projectionMatrix * outViewPosition;
}
