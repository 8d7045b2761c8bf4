// Idealized LV (Land et al. 2015; the built-in `lv` geometry) refined around an epicardial point
// (px, py, pz) mm: cells of hmin within rfine of it, growing to hmax beyond rcoarse. The same
// construction as ../lv_probe_refined.geo (the lv-probe reference), with the point a parameter.
SetFactory("OpenCASCADE");
DefineConstant[ hmin = 0.4, hmax = 3.0, rfine = 2.5, rcoarse = 9.0, px = 9.682, py = 0, pz = -5 ];
Sphere(1) = {0, 0, 0, 1};
Dilate {{0, 0, 0}, {10, 10, 20}} { Volume{1}; }
Sphere(2) = {0, 0, 0, 1};
Dilate {{0, 0, 0}, {7, 7, 17}} { Volume{2}; }
Box(3) = {-30, -30, 5, 60, 60, 30};
BooleanDifference(4) = { Volume{1}; Delete; }{ Volume{2}; Delete; };
BooleanDifference(5) = { Volume{4}; Delete; }{ Volume{3}; Delete; };
base() = Surface In BoundingBox{-11, -11, 4.99, 11, 11, 5.01};
endo() = Surface In BoundingBox{-7.01, -7.01, -17.01, 7.01, 7.01, 5.01};
all() = Boundary{ Volume{5}; };
epi() = all();
epi() -= base();
epi() -= endo();
Physical Surface("ENDO", 1) = endo();
Physical Surface("EPI", 2) = epi();
Physical Surface("BASE", 3) = base();
Physical Volume("MYOCARDIUM", 10) = {5};
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
