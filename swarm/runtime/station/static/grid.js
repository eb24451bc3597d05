/* A plain metric grid under the map tiles: what the page shows when no tile source
 * answers (a field without network at 6 a.m.), and what shows through where a tile
 * is missing.
 *
 * Theory of operation. gcsGrid.add(map, tileLayer) adds an L.GridLayer whose canvas
 * tiles are a flat ground with lines every S metres of ground, S one of 1, 2, 5 x 10^n
 * chosen so lines are at least MIN_PX pixels apart at the map's zoom and the latitude
 * of its centre (Web Mercator stretches the ground by 1 / cos(latitude); the grid is
 * redrawn when the centre's latitude moves enough to change that by more than 2 %).
 * A small control beside the scale bar names the spacing ("grid 50 m") until map
 * tiles are shown.
 *
 * Attribution is honest: the tile layer, if any, is created by initMap (app.js)
 * without attribution; its credit is added here only once one of its tiles has
 * actually loaded, and "no map tiles: grid" shows until then (offline, for ever).
 */
(function () {
  "use strict";
  const EARTH_M_PER_PX_Z0 = 156543.03392; // ground metres per pixel at zoom 0 on the equator
  const MIN_PX = 72;
  const NO_TILES = "no map tiles: grid";

  function spacingM(metresPerPx) {
    const want = metresPerPx * MIN_PX;
    let p = Math.pow(10, Math.floor(Math.log10(want)));
    for (;;) {
      for (const k of [1, 2, 5]) if (k * p >= want) return k * p;
      p *= 10;
    }
  }
  function label(m) {
    return m >= 1000 ? (m / 1000) + " km" : m + " m";
  }

  const Grid = L.GridLayer.extend({
    initialize(opts) {
      L.GridLayer.prototype.initialize.call(this, opts);
      this._cos = 1;
    },
    spacing(zoom) {
      const mpp = EARTH_M_PER_PX_Z0 * this._cos / Math.pow(2, zoom);
      const m = spacingM(mpp);
      return { m, px: m / mpp };
    },
    createTile(coords) {
      const tile = document.createElement("canvas");
      const size = this.getTileSize();
      tile.width = size.x;
      tile.height = size.y;
      const g = tile.getContext("2d");
      g.fillStyle = "#e9ece4";
      g.fillRect(0, 0, size.x, size.y);
      const s = this.spacing(coords.z);
      g.strokeStyle = "#b7beb2";
      g.lineWidth = 1;
      g.beginPath();
      const x0 = coords.x * size.x, y0 = coords.y * size.y;
      for (let gx = Math.ceil(x0 / s.px) * s.px; gx < x0 + size.x; gx += s.px) {
        const x = Math.round(gx - x0) + 0.5;
        g.moveTo(x, 0);
        g.lineTo(x, size.y);
      }
      for (let gy = Math.ceil(y0 / s.px) * s.px; gy < y0 + size.y; gy += s.px) {
        const y = Math.round(gy - y0) + 0.5;
        g.moveTo(0, y);
        g.lineTo(size.x, y);
      }
      g.stroke();
      tile.dataset.gridM = String(s.m);
      return tile;
    },
    follow(map) {
      const c = Math.max(0.01, Math.cos(map.getCenter().lat * Math.PI / 180));
      if (Math.abs(c - this._cos) / this._cos > 0.02) {
        this._cos = c;
        this.redraw();
      }
    },
  });

  const Legend = L.Control.extend({
    options: { position: "bottomleft" },
    onAdd() {
      const div = L.DomUtil.create("div", "leaflet-control-scale-line gcs-grid-legend");
      div.style.borderTop = "none";
      return div;
    },
  });

  function add(map, tileLayer, attribution) {
    const grid = new Grid({ zIndex: 0, maxZoom: 24, keepBuffer: 1 });
    grid.gridInfo = () => ({ spacing_m: grid.spacing(map.getZoom()).m, tiles_shown: !!grid.tilesShown });
    const legend = new Legend();
    const update = () => {
      grid.follow(map);
      const c = legend.getContainer();
      if (c) c.textContent = "grid " + label(grid.spacing(map.getZoom()).m);
    };
    map.whenReady(() => { grid.addTo(map); legend.addTo(map); update(); });
    map.on("moveend zoomend", update);
    map.attributionControl.addAttribution(NO_TILES);
    if (tileLayer) {
      tileLayer.on("tileload", (ev) => {
        // a tile that failed "loads" too, as the layer's errorTileUrl (a data: image)
        if (grid.tilesShown || !ev.tile || String(ev.tile.src).startsWith("data:")) return;
        grid.tilesShown = true;
        map.attributionControl.removeAttribution(NO_TILES);
        legend.remove(); // the grid now only fills the holes between tiles
        if (attribution) map.attributionControl.addAttribution(attribution);
      });
    }
    window.gcsGrid.layer = grid; // for tests and other page code
    window.gcsGrid.map = map;
    return grid;
  }

  window.gcsGrid = { add, spacingM };
})();
