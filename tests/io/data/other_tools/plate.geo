// a 2 x 1 plate, meshed with triangles (the area is the test's truth)
SetFactory("OpenCASCADE");
Rectangle(1) = {0, 0, 0, 2, 1};
Physical Surface("plate") = {1};
Mesh.MeshSizeMax = 0.5;
