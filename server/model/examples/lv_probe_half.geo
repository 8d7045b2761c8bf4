// Half of the idealized LV (../shared/data/lv/README.md; y >= 0, the plane y = 0 being a plane
// of mirror symmetry of the lv-probe press), meshed with element sizes s * clamp(r / r0, 1,
// phimax), r the distance to the lv-probe contact point (9.682458, 0, -5) mm: every size
// scales with s, so the levels of server/model/examples/lv_sphere_reference.sh are one
// systematically refined family. Groups ENDO, EPI, BASE (z = 5 mm), SYM (y = 0), MYOCARDIUM.
// gmsh lv_probe_half.geo -3 -format msh22 -setnumber s 0.3 -o half_0.3.msh
SetFactory("OpenCASCADE");
DefineConstant[ s = 0.6, r0 = 2.0, phimax = 6.0 ];
Sphere(1) = {0, 0, 0, 1};
Dilate {{0, 0, 0}, {10, 10, 20}} { Volume{1}; }
Sphere(2) = {0, 0, 0, 1};
Dilate {{0, 0, 0}, {7, 7, 17}} { Volume{2}; }
Box(3) = {-30, -30, 5, 60, 60, 30};
Box(6) = {-30, -30, -30, 60, 30, 60};
BooleanDifference(4) = { Volume{1}; Delete; }{ Volume{2}; Delete; };
BooleanDifference(5) = { Volume{4}; Delete; }{ Volume{3}; Delete; };
BooleanDifference(7) = { Volume{5}; Delete; }{ Volume{6}; Delete; };
// OpenCASCADE's bounding boxes of curved faces are loose, so the faces are told apart by
// their boxes' features: the base lies at z = 5, the symmetry face at y = 0, and the
// endocardium reaches down to z = -17 where the epicardium reaches z = -20.
all() = Boundary{ Volume{7}; };
base() = {}; sym() = {}; endo() = {}; epi() = {};
For k In {0:#all()-1}
  bb() = BoundingBox Surface{all(k)};
  If (bb(2) > 4.9)
    base() += all(k);
  ElseIf (bb(4) - bb(1) < 0.01)
    sym() += all(k);
  ElseIf (bb(2) > -18)
    endo() += all(k);
  Else
    epi() += all(k);
  EndIf
EndFor
Physical Surface("ENDO", 1) = endo();
Physical Surface("EPI", 2) = epi();
Physical Surface("BASE", 3) = base();
Physical Surface("SYM", 4) = sym();
Physical Volume("MYOCARDIUM", 10) = {7};
Field[1] = MathEval;
Field[1].F = Sprintf("%g * Min(%g, Max(1, Sqrt((x - 9.682458)^2 + y^2 + (z + 5)^2) / %g))", s, phimax, r0);
Background Field = 1;
Mesh.MeshSizeExtendFromBoundary = 0;
Mesh.MeshSizeFromPoints = 0;
Mesh.MeshSizeFromCurvature = 0;
Mesh.Algorithm3D = 1;
