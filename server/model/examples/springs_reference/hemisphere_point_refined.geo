// The solid half ball that hemisphere-springs' surface bounds (radius 50 mm about the origin,
// z >= 0), refined around a point (px, py, pz) mm of its dome: cells of hmin within rfine of
// it, growing to hmax beyond rcoarse. Dome "SURFACE" (touchable), flat face "BASE" (clamped).
SetFactory("OpenCASCADE");
DefineConstant[ hmin = 2.4, hmax = 12.0, rfine = 10.0, rcoarse = 30.0, px = 0, py = 0, pz = 50 ];
Sphere(1) = {0, 0, 0, 50};
Box(2) = {-60, -60, -60, 120, 120, 60};
BooleanDifference(3) = { Volume{1}; Delete; }{ Volume{2}; Delete; };
base() = Surface In BoundingBox{-51, -51, -0.01, 51, 51, 0.01};
all() = Boundary{ Volume{3}; };
dome() = all();
dome() -= base();
Physical Surface("SURFACE", 1) = dome();
Physical Surface("BASE", 2) = base();
Physical Volume("SOLID", 10) = {3};
Field[1] = MathEval;
Field[1].F = Sprintf("Sqrt((x - (%g))^2 + (y - (%g))^2 + (z - (%g))^2)", px, py, pz);
Field[2] = Threshold;
Field[2].InField = 1;
Field[2].SizeMin = hmin;
Field[2].SizeMax = hmax;
Field[2].DistMin = rfine;
Field[2].DistMax = rcoarse;
Background Field = 2;
Mesh.MeshSizeExtendFromBoundary = 0;
Mesh.MeshSizeFromPoints = 0;
Mesh.MeshSizeFromCurvature = 0;
Mesh.Algorithm3D = 1;
