// Wheel: zoom about the pointer; drag: pan; double-click: back to the whole figure.
(function () {
  document.querySelectorAll("svg.plot.zoom").forEach(function (svg) {
    var home = svg.getAttribute("viewBox").split(/[ ,]+/).map(Number);
    var vb = home.slice(), drag = null;
    function show() { svg.setAttribute("viewBox", vb.join(" ")); }
    function at(e) {
      var r = svg.getBoundingClientRect();
      return [vb[0] + (e.clientX - r.left) / r.width * vb[2], vb[1] + (e.clientY - r.top) / r.height * vb[3]];
    }
    svg.addEventListener("wheel", function (e) {
      e.preventDefault();
      var p = at(e), f = e.deltaY < 0 ? 0.8 : 1.25;
      vb = [p[0] - (p[0] - vb[0]) * f, p[1] - (p[1] - vb[1]) * f, vb[2] * f, vb[3] * f];
      if (vb[2] >= home[2]) { vb = home.slice(); }
      show();
    }, { passive: false });
    svg.addEventListener("mousedown", function (e) { drag = [e.clientX, e.clientY, vb[0], vb[1]]; e.preventDefault(); });
    window.addEventListener("mouseup", function () { drag = null; });
    svg.addEventListener("mousemove", function (e) {
      if (!drag) { return; }
      var r = svg.getBoundingClientRect();
      vb[0] = drag[2] - (e.clientX - drag[0]) / r.width * vb[2];
      vb[1] = drag[3] - (e.clientY - drag[1]) / r.height * vb[3];
      show();
    });
    svg.addEventListener("dblclick", function () { vb = home.slice(); show(); });
  });
})();
