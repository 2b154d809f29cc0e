<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>
<qgis hasScaleBasedVisibilityFlag="0" simplifyDrawingHints="1" symbologyReferenceScale="-1" version="3.22.16-Białowieża" simplifyAlgorithm="0" simplifyDrawingTol="1" simplifyMaxScale="1" minScale="100000000" simplifyLocal="1" styleCategories="Symbology|Symbology3D|Rendering" maxScale="0">
  <renderer-3d type="vector" layer="">
    <vector-layer-3d-tiling zoom-levels-count="3" show-bounding-boxes="0"/>
    <symbol type="polygon" material_type="phong">
      <data rendered-facade="3" invert-normals="0" alt-binding="centroid" alt-clamping="relative" extrusion-height="0" culling-mode="no-culling" height="0" add-back-faces="0"/>
      <material diffuse="70,120,24,255" specular="10,10,10,255" shininess="2" ambient="64,110,24,255">
        <data-defined-properties>
          <Option type="Map">
            <Option type="QString" value="" name="name"/>
            <Option name="properties"/>
            <Option type="QString" value="collection" name="type"/>
          </Option>
        </data-defined-properties>
      </material>
      <data-defined-properties>
        <Option type="Map">
          <Option type="QString" value="" name="name"/>
          <Option type="Map" name="properties">
            <Option type="Map" name="height">
              <Option type="bool" value="true" name="active"/>
              <Option type="QString" value="-coalesce(attribute('base_z'), z_min($geometry))" name="expression"/>
              <Option type="int" value="3" name="type"/>
            </Option>
          </Option>
          <Option type="QString" value="collection" name="type"/>
        </Option>
      </data-defined-properties>
      <edges enabled="0" width="1" color="0,0,0,255"/>
    </symbol>
  </renderer-3d>
  <renderer-v2 type="nullSymbol"/>
  <blendMode>0</blendMode>
  <featureBlendMode>0</featureBlendMode>
  <layerOpacity>1</layerOpacity>
  <layerGeometryType>2</layerGeometryType>
</qgis>
