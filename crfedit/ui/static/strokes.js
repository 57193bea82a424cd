// Strokes drawn over the rendered view: polylines with a radius, in the view's pixel units
// ((0, 0) the centre of the top-left pixel), exactly the --scribble-json form.
"use strict";

const Strokes = (() => {
  const COLORS = { fg: "rgba(230, 0, 170, 0.6)", bg: "rgba(40, 120, 255, 0.55)", copy: "rgba(250, 190, 0, 0.6)" };

  // The strokes JSON the server (and --scribble-json) reads: one radius for all when they agree.
  function toJson(list) {
    if (!list.length) return null;
    const r0 = list[0].radius;
    const pts = (s) => s.points.map(([x, y]) => [Math.round(x * 100) / 100, Math.round(y * 100) / 100]);
    if (list.every((s) => s.radius === r0)) return { strokes: list.map(pts), radius: r0 };
    return { strokes: list.map((s) => ({ points: pts(s), radius: s.radius })) };
  }

  function centroid(list) {
    let sx = 0, sy = 0, n = 0;
    for (const s of list) for (const [x, y] of s.points) { sx += x; sy += y; n += 1; }
    return n ? [sx / n, sy / n] : null;
  }

  // Distance from point p to segment ab.
  function segDist(p, a, b) {
    const abx = b[0] - a[0], aby = b[1] - a[1];
    const len = abx * abx + aby * aby;
    const t = len > 0 ? Math.max(0, Math.min(1, ((p[0] - a[0]) * abx + (p[1] - a[1]) * aby) / len)) : 0;
    return Math.hypot(p[0] - (a[0] + t * abx), p[1] - (a[1] + t * aby));
  }

  function touches(stroke, p, r) {
    const pts = stroke.points;
    if (pts.length === 1) return Math.hypot(p[0] - pts[0][0], p[1] - pts[0][1]) <= r + stroke.radius;
    for (let i = 1; i < pts.length; i++) if (segDist(p, pts[i - 1], pts[i]) <= r + stroke.radius) return true;
    return false;
  }

  // Draw strokes on a 2-D context whose pixels are `scale` canvas pixels per view pixel.
  function draw(ctx, list, kind, scale, shift = [0, 0], dashed = false) {
    ctx.save();
    ctx.strokeStyle = ctx.fillStyle = COLORS[kind];
    ctx.lineCap = ctx.lineJoin = "round";
    if (dashed) ctx.setLineDash([4, 4]);
    for (const s of list) {
      const pts = s.points.map(([x, y]) => [(x + 0.5 + shift[0]) * scale, (y + 0.5 + shift[1]) * scale]);
      ctx.lineWidth = 2 * s.radius * scale;
      ctx.beginPath();
      ctx.moveTo(pts[0][0], pts[0][1]);
      for (const [x, y] of pts.slice(1)) ctx.lineTo(x, y);
      if (pts.length === 1) ctx.lineTo(pts[0][0] + 0.01, pts[0][1]);
      ctx.stroke();
    }
    ctx.restore();
  }

  function marker(ctx, p, scale) {
    ctx.save();
    ctx.strokeStyle = "#111";
    ctx.lineWidth = 2;
    const [x, y] = [(p[0] + 0.5) * scale, (p[1] + 0.5) * scale];
    ctx.beginPath();
    ctx.moveTo(x - 8, y); ctx.lineTo(x + 8, y); ctx.moveTo(x, y - 8); ctx.lineTo(x, y + 8);
    ctx.stroke();
    ctx.restore();
  }

  return { toJson, centroid, touches, draw, marker };
})();
