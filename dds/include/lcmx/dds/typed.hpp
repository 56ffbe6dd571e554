// Typed mode at run time: a Cyclone DDS topic descriptor (dds_topic_descriptor_t, opcodes of
// dds_opcodes.h) built from an lcmx::types schema, and the conversion between LCM's encoding and
// a DDS sample laid out in memory as idlc's C for the same IDL (lcmx idl) would lay it out.
// Why at run time (docs/dds.md "Typed mode"): the gateway maps any type of its type path
// without a rebuild; a DDS program uses idlc's C for the IDL `lcmx idl` writes, and the two
// agree on the wire because both follow the same IDL.
//
// Memory layout (x86-64/aarch64 C ABI, as idlc's C): primitives at their natural alignment,
// string = char*, sequence = dds_sequence_t {uint32 max, uint32 len, void* buf, bool release},
// fixed arrays inline, nested structs inline; struct alignment = its largest member's.
// Thread safety: a TypedType is immutable after create(); its methods are const and reentrant.
#pragma once

#include <dds/dds.h>

#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "lcmx/types/schema.hpp"

namespace lcmx::dds {

class TypedType {
 public:
  // Throws types::Error for a type typed mode cannot map (check_typed).
  static std::unique_ptr<TypedType> create(const types::StructType& type, bool ros2);
  ~TypedType();
  TypedType(const TypedType&) = delete;
  TypedType& operator=(const TypedType&) = delete;

  // Valid as long as this object; pass to dds_create_topic.
  const dds_topic_descriptor_t* descriptor() const noexcept;
  const types::StructType& lcm_type() const noexcept { return *type_; }
  const std::string& dds_type_name() const noexcept { return name_; }
  std::size_t sample_size() const noexcept;
  // The descriptor's opcodes (as many words as descriptor()->m_ops holds).
  std::span<const std::uint32_t> ops() const noexcept { return ops_; }

  // A sample built from an LCM message: its memory and everything its pointers point to, owned
  // here (release flags false: DDS never frees them). Pass data() to dds_write.
  class Sample {
   public:
    const void* data() const noexcept { return memory_.data(); }

   private:
    friend class TypedType;
    std::vector<std::max_align_t> memory_;
    std::vector<std::unique_ptr<char[]>> blocks_;  // strings and sequence buffers
  };
  // LCM encoding (fingerprint first) -> sample. Throws types::Error (wrong fingerprint,
  // truncated, ...).
  Sample from_lcm(std::span<const std::byte> lcm) const;
  // A sample as DDS delivers it (laid out as descriptor() says) -> LCM encoding. A variable
  // array's size member is set from the sequence's length. Throws types::Error if arrays that
  // share a size member have different lengths, or a value is out of the LCM type's range.
  std::vector<std::uint8_t> to_lcm(const void* sample) const;

  struct Layout;  // private (typed.cpp)

 private:
  TypedType() = default;
  const types::StructType* type_ = nullptr;
  std::string name_;
  std::vector<std::uint32_t> ops_;
  std::unique_ptr<dds_topic_descriptor_t> desc_;
  std::vector<std::unique_ptr<Layout>> layouts_;  // [0] is the top-level type's
};

}  // namespace lcmx::dds
