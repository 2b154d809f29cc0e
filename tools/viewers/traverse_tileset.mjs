// Load a 3D Tiles tileset with loaders.gl and load + parse every tile's content.
// Usage: node traverse_tileset.mjs http://127.0.0.1:PORT/tileset.json   (or a file path)
// Prints one JSON line: {tiles, contents, triangles, nodes, errors:[...]}; exit 1 on any error.
import { load } from "@loaders.gl/core";
import { Tiles3DLoader } from "@loaders.gl/3d-tiles";
import { readFile } from "node:fs/promises";
import path from "node:path";

const target = process.argv[2];
const isUrl = /^https?:/.test(target);
const errors = [];
let tiles = 0, contents = 0, triangles = 0, nodes = 0;

async function fetchBytes(uri) {
  if (isUrl) {
    const r = await fetch(uri);
    if (!r.ok) throw new Error(`${uri}: HTTP ${r.status}`);
    return await r.arrayBuffer();
  }
  const b = await readFile(uri);
  return b.buffer.slice(b.byteOffset, b.byteOffset + b.byteLength);
}

function resolve(base, uri) {
  return isUrl ? new URL(uri, base).toString() : path.resolve(path.dirname(base), uri);
}

async function visit(tile, base) {
  tiles += 1;
  if (!tile.boundingVolume) errors.push(`tile ${tiles}: no boundingVolume`);
  const uri = tile.content?.uri;
  if (uri) {
    const url = resolve(base, uri);
    try {
      const content = await load(await fetchBytes(url), Tiles3DLoader, {
        "3d-tiles": { loadGLTF: true }, gltf: { loadImages: false, decompressMeshes: false },
      });
      contents += 1;
      const gltf = content.gltf;
      if (!gltf) throw new Error(`${uri}: no glTF in the parsed content (type ${content.type})`);
      nodes += (gltf.nodes || []).length;
      for (const mesh of gltf.meshes || []) {
        for (const prim of mesh.primitives) {
          if (!prim.attributes.POSITION) throw new Error(`${uri}: a primitive without POSITION`);
          triangles += (prim.indices ? prim.indices.count : prim.attributes.POSITION.count) / 3;
        }
      }
    } catch (e) {
      errors.push(`${uri}: ${e && e.message ? e.message : e}`);
    }
  }
  for (const child of tile.children || []) await visit(child, base);
}

try {
  const json = JSON.parse(new TextDecoder().decode(await fetchBytes(target)));
  if (!json.asset || !json.root) throw new Error("tileset.json has no asset or root");
  await visit(json.root, target);
  // loaders.gl's own tileset parser as well
  const ts = await load(await fetchBytes(target), Tiles3DLoader, { "3d-tiles": { isTileset: true }, baseUri: target });
  if (!ts.root) errors.push("Tiles3DLoader did not return a root tile");
} catch (e) {
  errors.push(String(e && e.stack ? e.stack : e));
}
console.log(JSON.stringify({ tiles, contents, triangles, nodes, errors }));
process.exit(errors.length ? 1 : 0);
